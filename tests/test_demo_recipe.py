"""The README's main job runs end to end (a short version) and reports consistent metrics."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "examples" / "demo_chain.py"


def test_demo_recipe_runs_and_writes_a_consistent_summary(tmp_path):
    spec = importlib.util.spec_from_file_location("demo_chain", RECIPE)
    demo = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(demo)
    summary = demo.main(["--steps", "400", "--heat-up", "50", "--hidden", "16", "--members", "2", "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["steps"] == 400 == summary["forward_steps"] + summary["reset_steps"]
    assert saved["reset_episodes"] == saved["successful_resets"] + saved["manual_resets"]
    assert 0.0 <= saved["forward_share"] <= 1.0
    assert set(saved["evaluation"]) >= {"forward_return", "furthest_cell", "fell_in_ditch"}
