"""report.py on small fabricated run folders: Table 1 numbers worked out by hand, and the figures."""
from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import matplotlib.image as mpimg
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "recipes"))

import report  # noqa: E402


def fabricate(root: Path, task, algo, seed, p_thresh, avg_return, manual, share, success, steps=1000):
    folder = root / task / algo / f"p{p_thresh}" / f"seed{seed}"
    folder.mkdir(parents=True)
    summary = {"task": task, "algo": algo, "seed": seed, "p_thresh": p_thresh, "steps": steps,
               "average_return": avg_return, "manual_resets": manual, "forward_share": share, "reset_success_rate": success}
    (folder / "summary.json").write_text(json.dumps(summary))
    tables = {
        "progress.csv": (["frames", "manual_resets"], [(f, manual * f // steps) for f in range(250, steps + 1, 250)]),
        "eval.csv": (["frames", "forward_return"], [(f, avg_return * f / steps) for f in range(500, steps + 1, 500)]),
        "triggers.csv": (["frames", "steps", "value", "observation"], [(f, 10, 0.01 * f, "0 0") for f in range(100, steps, 100)]),
    }
    for name, (header, rows) in tables.items():
        with open(folder / name, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(header)
            writer.writerows(rows)
    return folder


def test_table1_and_figures_from_fabricated_runs(tmp_path):
    runs = tmp_path / "runs"
    folder = fabricate(runs, "cliff_cheetah", "ours", 0, 0.05, 2.0, 10, 0.3, 0.9)
    with open(folder / "diagnostics.csv", "w", newline="") as f:
        csv.writer(f).writerows([["frames", "trigger_score_mean", "trigger_score_min", "example_p", "forward_p"],
                                 [500, 0.8, 0.5, 0.99, 0.6], [1000, 0.4, 0.05, 0.98, 0.3]])
    with open(folder / "resets.csv", "w", newline="") as f:
        csv.writer(f).writerows([["frames", "outcome", "steps", "distance_to_start", "distance_to_examples"],
                                 [300, "manual", 200, 2.0, 1.5], [900, "success", 20, 0.1, 0.0]])
    fabricate(runs, "cliff_cheetah", "ours", 1, 0.05, 4.0, 30, 0.5, 1.0)
    fabricate(runs, "cliff_cheetah", "ours", 0, 0.2, 1.0, 5, 0.1, 0.5)
    fabricate(runs, "cliff_cheetah", "lnt", 0, 0.05, 5.0, 100, 0.2, 0.8)
    written = report.report([runs], tmp_path / "out")
    table = (tmp_path / "out" / "table1.md").read_text()
    # seeds 0 and 1: returns 2 and 4 -> 3.00 ± 1.00; manual 10, 30 -> 20 ± 10; shares 0.3, 0.5 -> 40.0% ± 10.0;
    # success 0.9, 1.0 -> 95.0% ± 5.0 (population standard deviation); the paper's cliff-cheetah row beside
    assert ("| cliff-cheetah | ours | 0.05 | 2 | 1000 | 3.00 ± 1.00 (paper 1.96) | 20 ± 10 (paper 371) | "
            "40.0% ± 10.0 (paper 31.4%) | 95.0% ± 5.0 (paper 94.8%) |") in table
    assert "| cliff-cheetah | LNT | 0.05 | 1 | 1000 | 5.00 ± 0.00 (paper 4.77) |" in table
    assert "| cliff-cheetah | ours | 0.2 | 1 |" in table
    names = {kind: [p.name for p in paths] for kind, paths in written.items()}
    assert names["fig3"] == ["fig3_cliff_cheetah.png"]
    assert names["diagnostics"] == ["diagnostics_cliff_cheetah_ours.png"]  # only that run logged diagnostics
    assert names["fig4"] == ["fig4_cliff_cheetah_ours.png"]  # only ours has two p_thresh values
    assert sorted(names["fig5"]) == ["fig5_cliff_cheetah_lnt.png", "fig5_cliff_cheetah_ours.png"]
    for paths in written.values():
        for path in paths:
            if path.suffix == ".png":
                assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
                assert mpimg.imread(path).std() > 0.01  # something was drawn


def test_report_without_runs_and_with_a_foreign_summary(tmp_path):
    with pytest.raises(SystemExit, match="no summary.json"):
        report.report([tmp_path])
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "summary.json").write_text(json.dumps({"task": "t"}))
    with pytest.raises(ValueError, match="not written by train.py"):
        report.report([tmp_path])


def test_a_budget_compares_runs_as_they_stood_at_that_step(tmp_path):
    folder = tmp_path / "runs" / "peg_insertion_insert" / "ours" / "seed0"
    folder.mkdir(parents=True)
    summary = {"task": "peg_insertion_insert", "algo": "ours", "seed": 0, "p_thresh": 0.1, "steps": 4000,
               "average_return": 9.0, "manual_resets": 99, "forward_share": 0.9, "reset_success_rate": 0.9}
    (folder / "summary.json").write_text(json.dumps(summary))
    header = ["frames", "forward_steps", "reset_steps", "forward_episodes", "successful_resets", "manual_resets",
              "triggered_resets"]
    rows = [(1000, 300, 700, 3, 0, 3, 1), (2000, 800, 1200, 8, 2, 5, 2), (3000, 1500, 1500, 15, 6, 7, 9),
            (4000, 2400, 1600, 24, 14, 8, 9)]
    with open(folder / "progress.csv", "w", newline="") as f:
        csv.writer(f).writerows([header, *rows])
    with open(folder / "eval.csv", "w", newline="") as f:
        csv.writer(f).writerows([["frames", "forward_return"], [1000, 1.0], [2000, 2.0], [3000, 6.0], [4000, 30.0]])
    (folder / "config.yaml").write_text("task: {forward_horizon: 60}\n")
    report.report([tmp_path / "runs"], tmp_path / "out", budget=3000)
    table = (tmp_path / "out" / "table1.md").read_text()
    # at 3000 steps: return mean(1, 2, 6) = 3.00; manual 7; share 1500 / 3000 = 50.0%; success 6 / 13 = 46.2%
    assert "| peg-insertion (insert) | ours | 0.1 | 1 | 3000 | 3.00 ± 0.00 (paper 29.20) | 7 ± 0 (paper 343) | " \
           "50.0% ± 0.0 (paper 66.3%) | 46.2% ± 0.0 (paper 96.6%) |" in table
    # 15 forward episodes, 15 - 7 = 8 saved; last quarter of 3000 steps from the row at 2000 (the last at or
    # before 2250): (7 - 5) manual resets in 1000 steps = 2.00 per 1k
    # the release's baseline: (1500 forward steps + 9 triggered calls) // H_f = 60 gives 25, 25 - 7 = 18 saved
    assert "| peg-insertion (insert) | ours | 0.1 | 1 | 7 ± 0 | 15 ± 0 | 8 ± 0 | 25 ± 0 | 18 ± 0 | 2.00 ± 0.00 |" in table
    assert "at a budget of 3000 steps" in table


def test_a_run_still_going_is_read_from_its_config_and_logs(tmp_path):
    folder = tmp_path / "runs" / "cliff_cheetah" / "lnt" / "seed2"
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text("seed: 2\ntask: {name: cliff_cheetah, p_thresh: 0.05}\nalgo: {name: lnt}\n")
    with open(folder / "progress.csv", "w", newline="") as f:
        csv.writer(f).writerows([["frames", "forward_steps", "reset_steps", "forward_episodes", "successful_resets",
                                  "manual_resets"], [500, 100, 400, 2, 1, 3], [1000, 250, 750, 5, 3, 4]])
    run, = report.find_runs([tmp_path / "runs"])
    # as it stands at 1000 steps: share 250 / 1000, success 3 / 7, no evaluation yet
    assert run.summary["steps"] == 1000 and run.summary["manual_resets"] == 4 and not run.summary["finished"]
    assert run.summary["forward_share"] == pytest.approx(0.25) and run.summary["reset_success_rate"] == pytest.approx(3 / 7)
    assert run.summary["episodic_resets"] == 5


def test_runs_short_of_the_budget_are_left_out_of_their_groups_means(tmp_path):
    runs = tmp_path / "runs"
    # two seeds of ours: seed 0 reached 1000 steps with 40 manual resets, seed 1 only 500 (10 so far)
    fabricate(runs, "peg_insertion_insert", "ours", 0, 0.1, 2.0, 40, 0.5, 0.5, steps=1000)
    fabricate(runs, "peg_insertion_insert", "ours", 1, 0.1, 1.0, 20, 0.5, 0.5, steps=1000)
    with open(runs / "peg_insertion_insert" / "ours" / "p0.1" / "seed1" / "progress.csv", "w", newline="") as f:
        csv.writer(f).writerows([["frames", "manual_resets"], [250, 5], [500, 10]])
    # LNT has no run at the budget: its row is kept, marked in progress
    fabricate(runs, "peg_insertion_insert", "lnt", 0, 0.1, 1.0, 8, 0.5, 0.5, steps=1000)
    with open(runs / "peg_insertion_insert" / "lnt" / "p0.1" / "seed0" / "progress.csv", "w", newline="") as f:
        csv.writer(f).writerows([["frames", "manual_resets"], [250, 3], [750, 6]])
    report.report([runs], tmp_path / "out", budget=1000)
    table = (tmp_path / "out" / "table1.md").read_text()
    assert "| peg-insertion (insert) | ours | 0.1 | 1 | 1000 |" in table  # seed 1 out of the mean: 40, not 25
    assert "| ours | 0.1 | 1 | 40 ± 0 |" in table
    assert "| peg-insertion (insert) | LNT | 0.1 | 1 | 750 (in progress) |" in table
    assert "Left out of the means, still short of the budget: ours seed 1 at 500 steps." in table
    # Fig. 3 draws the same runs: ours from seed 0 alone, LNT's only run marked in progress
    groups = report.figure3_groups(report.find_runs([runs], budget=1000))
    assert [r.summary["seed"] for r in groups["ours"][0]] == [0] and groups["ours"][1] == "ours"
    assert [r.summary["seed"] for r in groups["lnt"][0]] == [0] and groups["lnt"][1] == "LNT, in progress"


def test_step_axes_read_in_thousands_and_millions():
    assert [report._steps_label(v) for v in (0, 500, 2000, 12500, 150000, 1.5e6)] == ["0", "500", "2k", "12.5k", "150k", "1.5M"]


def _config_yaml(*overrides: str, drop: str | None = None) -> str:
    """A run's config.yaml as train.py writes it (the composed recipe config, resolved), with ``drop``
    removed as from a config written before that setting existed."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf, open_dict

    with initialize_config_dir(config_dir=str(Path(report.__file__).parent / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["task=peg_insertion_insert", "algo=ours", *overrides])
    if drop is not None:
        section, key = drop.split(".")
        with open_dict(cfg):
            del cfg[section][key]
    return OmegaConf.to_yaml(cfg, resolve=True)


def test_runs_with_different_settings_are_kept_apart_and_named_by_what_they_changed(tmp_path):
    runs = tmp_path / "runs"
    task = "peg_insertion_insert"
    # seeds 0 and 1 at the paper's setting; seed 1 ran with other bookkeeping (threads, length, folder,
    # speed paths, logging) and from a config written before algo.initial_logit_bias existed: still one setting
    a = fabricate(runs, task, "ours", 0, 0.1, 2.0, 10, 0.3, 0.9)
    (a / "config.yaml").write_text(_config_yaml("seed=0", "threads=1"))
    b = fabricate(runs, task, "ours", 1, 0.1, 4.0, 30, 0.5, 1.0)
    (b / "config.yaml").write_text(_config_yaml(
        "seed=1", "threads=2", "total_steps=5000", "sweep_dir=elsewhere", "resume=auto", "speed.batched_acting=true",
        "checkpoint_every=777", "log_every=10", drop="algo.initial_logit_bias"))
    # two options, one seed each: a pessimistic start, and a smaller prior scale with it
    c = fabricate(runs, task, "ours", 2, 0.1, 1.0, 50, 0.1, 0.2)
    (c / "config.yaml").write_text(_config_yaml("seed=2", "algo.initial_logit_bias=-4"))
    d = fabricate(runs, task, "ours", 3, 0.1, 3.0, 70, 0.2, 0.4)
    (d / "config.yaml").write_text(_config_yaml("seed=3", "algo.initial_logit_bias=-4", "algo.prior_scale=1.0"))
    written = report.report([runs], tmp_path / "out")
    table = (tmp_path / "out" / "table1.md").read_text()
    # seeds 0 and 1 averaged (returns 2, 4 -> 3.00 ± 1.00; manual 10, 30 -> 20 ± 10), the paper's numbers beside
    assert ("| peg-insertion (insert) | ours (paper's setting) | 0.1 | 2 | 1000 | 3.00 ± 1.00 (paper 29.20) | "
            "20 ± 10 (paper 343) |") in table
    # each option alone, named by what it changed from the recipe's defaults, no paper numbers beside it
    assert ("| peg-insertion (insert) | ours (algo.initial_logit_bias=-4) | 0.1 | 1 | 1000 | 1.00 ± 0.00 | "
            "50 ± 0 | 10.0% ± 0.0 | 20.0% ± 0.0 |") in table
    assert ("| peg-insertion (insert) | ours (algo.initial_logit_bias=-4, algo.prior_scale=1.0) | 0.1 | 1 | 1000 | "
            "3.00 ± 0.00 | 70 ± 0 |") in table
    assert table.index("ours (paper's setting)") < table.index("ours (algo.initial_logit_bias=-4)")
    groups = report.figure3_groups(report.find_runs([runs]))
    assert {key: sorted(r.summary["seed"] for r in members) for key, (members, _) in groups.items()} == {
        "ours (paper's setting)": [0, 1], "ours (algo.initial_logit_bias=-4)": [2],
        "ours (algo.initial_logit_bias=-4, algo.prior_scale=1.0)": [3]}
    assert sorted(p.name for p in written["fig5"]) == [
        "fig5_peg_insertion_insert_ours.png", "fig5_peg_insertion_insert_ours_algo.initial_logit_bias-4.png",
        "fig5_peg_insertion_insert_ours_algo.initial_logit_bias-4_algo.prior_scale1.0.png"]
    # without the options the same two runs are one group and the table reads as before
    for folder in (c, d):
        for path in folder.iterdir():
            path.unlink()
        folder.rmdir()
    report.report([runs], tmp_path / "alone")
    assert "| peg-insertion (insert) | ours | 0.1 | 2 | 1000 | 3.00 ± 1.00 (paper 29.20) |" in (
        tmp_path / "alone" / "table1.md").read_text()
