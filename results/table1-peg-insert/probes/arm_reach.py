"""Frozen: its question is decided. It last ran at commit 271779f, as results/100000-release/probes/arm_reach.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/100000-release/probes/arm_reach.py --help``.

How far the same exploration carries the peg in tier 1's arm and in the release's: a physics check.

    python results/table1-peg-insert/probes/arm_reach.py --episodes 50 --out results/table1-peg-insert/probes/arm_reach.csv

Tier 1 ran the peg tasks on the model this project had before commit ``d7b4986`` (gymnasium's pusher arm
with edits, actions scaled to the motors' +-2); tier 1 at the release's settings runs the model written
from the release's parameters, actions in [-1, 1] sent unscaled. This probe builds both from this
repository's own history (``git show d7b4986~1:envs/...`` into a temporary package; nothing is kept),
and drives each from the insert task's start for one forward episode (H_f = 100 steps) with the same
torques:

- ``noise``: the recipe's Ornstein-Uhlenbeck noise alone (theta 0.15, sigma 0.2, dt 0.05, from zero),
  the same torque sequence in both models (in both, the noise is added in torque units);
- ``policy + noise``: an untrained actor's constant output m (per joint U(-0.5, 0.5)) plus that noise;
  tier 1's actor was scaled to +-2 (torque 2 m + noise), the release's is not (m + noise).

Per episode: the distance of the peg's two ends from their start positions after 100 steps (``d_start``;
the insert task's reset succeeds below 0.2) and the largest joint-angle change. Printed per model and
condition: medians, the share of episodes still within the reset check (``d_start < 0.2``) at the end.
"""
from __future__ import annotations

import argparse
import csv
import importlib
import importlib.util
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[3]
BEFORE = "d7b4986~1"  # the last commit with tier 1's peg model


def tier1_env_class():
    """Tier 1's PegInsertionEnv, built from the repository's history into a temporary package."""
    folder = Path(tempfile.mkdtemp(prefix="peg_tier1_"))
    package = folder / "peg_tier1"
    package.mkdir()
    (package / "__init__.py").write_text("")
    for name in ("_mujoco.py", "peg.py"):
        source = subprocess.run(["git", "-C", str(REPO), "show", f"{BEFORE}:envs/{name}"], check=True,
                                capture_output=True, text=True).stdout
        (package / name).write_text(source)
    # the old package loaded from its folder under its own name (it imports its modules relatively)
    spec = importlib.util.spec_from_file_location("peg_tier1", package / "__init__.py",
                                                  submodule_search_locations=[str(package)])
    sys.modules["peg_tier1"] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sys.modules["peg_tier1"])
    return importlib.import_module("peg_tier1.peg").PegInsertionEnv


def ou_noise(rng: np.random.Generator, steps: int, dims: int, theta=0.15, sigma=0.2, dt=0.05) -> np.ndarray:
    x, out = np.zeros(dims), np.empty((steps, dims))
    for t in range(steps):
        x = x + theta * (0.0 - x) * dt + sigma * np.sqrt(dt) * rng.standard_normal(dims)
        out[t] = x
    return out


def episode(env, torques: np.ndarray) -> dict:
    obs, _ = env.reset(seed=0)
    q0 = obs[:7].copy()
    for torque in torques:
        obs, *_ = env.step(torque.astype(np.float32))
    return {"d_start": env.d_start(), "joint_change": float(np.abs(obs[:7] - q0).max())}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--out", type=Path, default=None, help="a CSV of every episode")
    args = parser.parse_args(argv)
    from torchrl_reset_envs import PegInsertionEnv

    models = {"tier 1": (tier1_env_class()("insert"), 2.0), "release": (PegInsertionEnv("insert"), 1.0)}
    rows = []
    for k in range(args.episodes):
        rng = np.random.default_rng(k)
        noise = ou_noise(rng, args.steps, 7)
        mean = rng.uniform(-0.5, 0.5, 7)
        for model, (env, scale) in models.items():
            for condition, torques in (("noise", noise), ("policy + noise", scale * mean + noise)):
                rows.append({"episode": k, "model": model, "condition": condition, **episode(env, torques)})
    print(f"{args.episodes} episodes of {args.steps} steps from the insert task's start\n")
    print("| model | condition | median d_start after the episode | still within d_start < 0.2 | median largest joint change (rad) |")
    print("|---|---|---|---|---|")
    for condition in ("noise", "policy + noise"):
        for model in models:
            mine = [r for r in rows if r["model"] == model and r["condition"] == condition]
            d = np.array([r["d_start"] for r in mine])
            q = np.array([r["joint_change"] for r in mine])
            print(f"| {model} | {condition} | {np.median(d):.3f} | {np.mean(d < 0.2):.0%} | {np.median(q):.3f} |")
    if args.out is not None:
        with open(args.out, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
