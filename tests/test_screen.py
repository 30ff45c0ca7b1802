"""The screening command (recipes/analysis/screen.py): seeds, the grid's command, the per-seed entries, the interval and
the table, on run folders made here with counts chosen by hand."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest


from torchrl_reset_recipes.analysis import screen


def test_seed_lists_and_ranges():
    assert screen.seed_list("0-3") == [0, 1, 2, 3]
    assert screen.seed_list("10-12,15") == [10, 11, 12, 15]
    with pytest.raises(ValueError, match="seeds must be"):
        screen.seed_list("a-b")


def test_the_grid_is_one_hydra_multirun_with_one_thread_per_run_and_resume_auto():
    command = screen.grid_command("preact", [0, 1], ["preset=quick"], "runs/screening", 2)
    assert command[1].endswith("train.py") and command[2] == "-m"
    assert {"preset=quick", "seed=0,1", "threads=1", "resume=auto", "hydra.launcher.n_jobs=2",
            "run_dir=runs/screening/preact/seed${seed}"} <= set(command)
    with pytest.raises(ValueError, match="one folder name"):
        screen.grid_command("a/b", [0], [], "runs", 1)


def test_run_takes_the_recipes_overrides_after_a_double_dash(monkeypatch):
    called = []
    monkeypatch.setattr(screen.subprocess, "call", lambda command: called.append(command) or 0)
    with pytest.raises(SystemExit) as stop:
        screen.main(["run", "clip", "--seeds", "3-4", "--jobs", "1", "--", "preset=quick", "exploration.clip=true"])
    assert stop.value.code == 0
    assert {"preset=quick", "exploration.clip=true", "seed=3,4", "hydra.launcher.n_jobs=1"} <= set(called[0])


def test_the_interval_brackets_the_mean_and_needs_three_values():
    mean, low, high = screen.bootstrap_interval([1.0, 2.0, 3.0, 4.0, 10.0])
    assert mean == pytest.approx(4.0) and low < 4.0 < high
    assert low >= 1.0 and high <= 10.0  # a bootstrap mean never leaves the data's range
    assert screen.bootstrap_interval([5.0, 5.0, 5.0]) == (5.0, 5.0, 5.0)
    mean, low, high = screen.bootstrap_interval([2.0, float("nan"), 4.0])
    assert mean == 3.0 and math.isnan(low) and math.isnan(high)


def _run(folder: Path, seed: int, manual: int, last: float | None, share: float, saturation: float,
         forward_saturation: float | None = None):
    folder.mkdir(parents=True)
    quarter = {"reset_saturation": saturation}
    if forward_saturation is not None:  # runs before the forward actor's column have none
        quarter["forward_saturation"] = forward_saturation
    (folder / "summary.json").write_text(json.dumps({
        "seed": seed, "steps": 1000, "finished": True, "manual_resets": manual, "episodic_resets": 50,
        "reset_success_rate_first_quarter": 0.25, "reset_success_rate_last_quarter": last, "forward_share": share,
        "saturation": {"last_quarter": quarter}}))
    # evaluations at 500 and 1000 steps: only the one in the last quarter (> 750) counts
    (folder / "eval.csv").write_text("frames,forward_return\n500,9.0\n1000,3.0\n")


def test_the_table_counts_the_seeds_that_hold_and_shows_every_seed(tmp_path):
    _run(tmp_path / "a" / "seed0", 0, 10, 0.5, 0.2, 0.1)  # holds: exactly 50%
    _run(tmp_path / "a" / "seed1", 1, 30, 0.49, 0.1, 0.6, forward_saturation=0.9)
    _run(tmp_path / "a" / "seed2", 2, 20, None, 0.3, 0.2)  # no reset episode in its last quarter
    rows = screen.read_configuration(tmp_path / "a")
    assert [r["seed"] for r in rows] == [0, 1, 2]
    assert [screen.holds(r) for r in rows] == [True, False, False]
    assert rows[0]["forward_return"] == 3.0
    table = screen.screening_table({"a": rows})
    assert "| a | 3 (0,1,2) | 1 of 3 |" in table
    assert "| 20 [" in table  # mean manual resets (10 + 30 + 20) / 3 with its interval
    assert "| a | 1 | 1000 | no | 30 | 50 | 25% | 49% | 10% | 3.00 | 60% | 90% |" in table
    assert "| a | 0 | 1000 | yes | 10 | 50 | 25% | 50% | 20% | 3.00 | 10% | n/a |" in table  # not logged: n/a
    fig = screen.screening_figure({"a": rows, "b": rows})
    assert len(fig.axes) == 4
    screen.main(["table", str(tmp_path), "--out", str(tmp_path / "out")])
    assert (tmp_path / "out" / "screening.md").exists() and (tmp_path / "out" / "screening.png").exists()
    assert np.isclose(screen.bootstrap_interval([r["manual_resets"] for r in rows])[0], 20.0)


def test_the_table_puts_folders_made_elsewhere_side_by_side(tmp_path):
    """--config NAME=FOLDER: two results folders' runs as two configurations, in the order given, beside root's or
    without one; a malformed pair, an --order naming no configuration, or nothing to read are refused."""
    _run(tmp_path / "old" / "ours" / "seed0", 0, 300, 0.8, 0.25, 0.5)
    _run(tmp_path / "new" / "ours" / "seed0", 0, 200, 0.9, 0.2, 0.0)
    out = tmp_path / "out"
    screen.main(["table", "--config", f"release={tmp_path / 'old' / 'ours'}",
                 "--config", f"project={tmp_path / 'new' / 'ours'}", "--out", str(out)])
    table = (out / "screening.md").read_text()
    assert table.index("| release | 0 | 1000 | yes | 300 |") < table.index("| project | 0 | 1000 | yes | 200 |")
    screen.main(["table", str(tmp_path / "old"), "--config", f"project={tmp_path / 'new' / 'ours'}",
                 "--order", "project,ours", "--out", str(out)])
    table = (out / "screening.md").read_text()
    assert table.index("| project | 0 |") < table.index("| ours | 0 |")
    for bad in (["table", "--config", "release", "--out", str(out)],  # no folder
                ["table", "--config", f"release={tmp_path / 'old' / 'ours'}"],  # no --out and no root
                ["table", "--config", f"a={tmp_path / 'old' / 'ours'}", "--order", "b", "--out", str(out)],
                ["table"]):
        with pytest.raises(SystemExit) as refused:
            screen.main(bad)
        assert refused.value.code == 2
