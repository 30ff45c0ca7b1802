"""The way off one machine: the documented Slurm command composes, and a grid runs through Hydra's submitit
launcher (its local executor: the same code path as Slurm without the queue), every run's summary read back."""
from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import QUICK_TINY

ROOT = Path(__file__).resolve().parents[1]
TRAIN = ROOT / "recipes" / "train.py"


def documented_slurm_command() -> list[str]:
    """The arguments of docs/many-runs.md's Slurm command (its ``python recipes/train.py -m`` block)."""
    page = (ROOT / "docs" / "many-runs.md").read_text()
    block = re.search(r"```bash\n(?:pip install[^\n]*\n)?(python recipes/train\.py -m hydra/launcher=submitit_slurm.*?)```",
                      page, re.S)
    assert block, "docs/many-runs.md has no Slurm command block"
    return shlex.split(block.group(1).replace("\\\n", " "))[2:]  # after "python recipes/train.py"


def test_the_documented_slurm_command_composes_with_the_slurm_launchers_settings():
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    args = documented_slurm_command()
    assert args[0] == "-m"
    # --cfg hydra composes one job: each swept key takes its first value, a placeholder becomes a name
    single = [re.sub(r"=([^,]*),.*", r"=\1", a).replace("<yours>", "main") for a in args[1:]]
    out = subprocess.run([sys.executable, str(TRAIN), *single, "--cfg", "hydra"], capture_output=True, text=True,
                         cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "SlurmLauncher" in out.stdout and "partition: main" in out.stdout
    assert "n_jobs" not in out.stdout  # joblib's settings stay with joblib


def test_a_grid_runs_through_the_submitit_launcher_and_every_summary_is_read(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    grid = [sys.executable, str(TRAIN), "-m", "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=20",
            *QUICK_TINY, "total_steps=120", "seed=0,1", f"sweep_dir={tmp_path}"]
    out = subprocess.run(grid, capture_output=True, text=True, cwd=ROOT, timeout=900)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    summaries = {seed: json.loads((tmp_path / "ball_in_cup_catch" / "ours" / f"seed{seed}" / "summary.json").read_text())
                 for seed in (0, 1)}
    for seed, summary in summaries.items():
        assert summary["finished"] and summary["steps"] == 120, (seed, summary)
        assert 0 <= summary["manual_resets"] <= summary["episodic_resets"]  # at most one per forward episode
    assert list(tmp_path.glob("multirun/*/.submitit")), "the submitit launcher's own files are where Hydra puts them"
