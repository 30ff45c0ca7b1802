"""The grid through Hydra's launcher: one -m command runs every (algo, seed) in parallel local
processes, each in its own run folder, and report.py reads the sweep folder as it is."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from torchrl_reset_recipes.analysis import report

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
TINY = [
    "hidden_sizes=[16,16]", "heat_up=40", "task.forward_horizon=20", "forward.batch_size=16", "reset.batch_size=16",
    "forward.buffer_size=2000", "reset.buffer_size=2000", "eval_every=100", "log_every=50", "checkpoint_every=100",
    "progress_bar=false", "total_steps=100",
]


def test_a_tiny_grid_runs_through_the_local_launcher_and_the_report_reads_it(tmp_path):
    sweep = tmp_path / "sweep"
    command = [sys.executable, str(RECIPES / "train.py"), "-m", "task=ball_in_cup_catch", "algo=ours,lnt_sparse",
               "seed=0", f"sweep_dir={sweep}", *TINY]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    runs = sorted(p.parent.relative_to(sweep).as_posix() for p in sweep.glob("*/*/*/summary.json"))
    assert runs == [f"ball_in_cup_catch/{algo}/seed0" for algo in ("lnt_sparse", "ours")]
    for run in runs:
        summary = json.loads((sweep / run / "summary.json").read_text())
        assert summary["steps"] == 100 and summary["finished"]
        assert (sweep / run / "config.yaml").exists() and (sweep / run / "code.jsonl").exists()
    # Hydra's own files go beside the runs, one folder per job
    assert len(list(sweep.glob("multirun/*/*/.hydra"))) == 2
    # relaunching the same grid with resume=auto continues each run from its checkpoint (through Hydra's basic
    # launcher, one process: the resume does not depend on the launcher, and the joblib workers' start is not repeated)
    again = subprocess.run([*command, "resume=auto", "total_steps=150", "hydra/launcher=basic"], capture_output=True,
                           text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    for run in runs:
        summary = json.loads((sweep / run / "summary.json").read_text())
        assert summary["steps"] == 150
        assert [json.loads(line)["from_step"] for line in (sweep / run / "code.jsonl").read_text().splitlines()] == [0, 100]
    report.main([str(sweep), "--out", str(tmp_path / "report")])  # as `python recipes/analysis/report.py` runs it
    table = (tmp_path / "report" / "table1.md").read_text()
    assert "| ours |" in table and "| LNT-sparse |" in table
    assert (tmp_path / "report" / "fig3_ball_in_cup_catch.png").exists()
