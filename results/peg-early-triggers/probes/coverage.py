"""Frozen: its question is decided. It last ran at commit 271779f, as results/peg-early-triggers/probes/coverage.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/peg-early-triggers/probes/coverage.py --help``.

Where the reset agent's classifiers get their rows from: how far from the start the states of each agent's
replay rows lie, for the rows written in a stretch of a run.

    python results/peg-early-triggers/probes/coverage.py \\
        runs/100k-tanh_normal_auto/peg_insertion_insert/ours/seed0 runs/peg-early-triggers/release_actor/peg_insertion_insert/ours/seed0

For each run folder of peg insertion (insert), from the replay buffers of its latest checkpoint (which must
still hold the stretch's rows) and its ``progress.csv``: the rows written from ``--start`` to ``--end`` steps
(default 30,000-50,000), the reset agent's and the forward agent's apart, and for each the share of row states
inside the task's at-initial-state check (``d_start < 0.2``, the peg's distance from its start worked out from
the arm's joint positions on the task's model, as ``measure.py`` does) and the quartiles of ``d_start``.

A buffer is in the order it was written. The reset agent's rows of the stretch are found from ``progress.csv``'s
``reset_steps`` at ``--start`` and ``--end`` (its buffer holds reset steps only); with ``reset.learn_from_forward``
the reset buffer holds every step and the rows of the stretch are found from the frames, those of a forward
episode (a ``traj_ids`` value of the forward buffer) counted as the forward agent's. The rows written just
before a checkpoint whose n-step window had not closed are not in the buffer: a few rows at most.
"""
from __future__ import annotations

import argparse
import runpy
from pathlib import Path

import numpy as np
import torch

from torchrl_reset_envs import PegInsertionEnv
from torchrl_reset_recipes.analysis.saved_runs import load_replay, run_config, run_table

_measure = runpy.run_path(str(Path(__file__).with_name("measure.py")))  # the check, worked out as measure.py does
CHECK, d_start = _measure["CHECK"], _measure["d_start"]


def rows_at(progress: list[dict], frames: int, key: str) -> int:
    """``key`` of the last ``progress.csv`` row at or before ``frames`` steps."""
    before = [r for r in progress if int(r["frames"]) <= frames]
    if not before or int(before[-1]["frames"]) != frames:
        raise SystemExit(f"progress.csv has no row at {frames} steps (rows every log_every steps)")
    return int(float(before[-1][key]))


def describe(env: PegInsertionEnv, observations: torch.Tensor) -> dict:
    if len(observations) == 0:
        return {"rows": 0}
    d = np.array([d_start(env, o[:7].double().numpy()) for o in observations])
    q1, median, q3 = np.quantile(d, [0.25, 0.5, 0.75])
    return {"rows": len(d), "inside": float(np.mean(d < CHECK)), "q1": q1, "median": median, "q3": q3}


def coverage(env: PegInsertionEnv, run: Path, start: int, end: int) -> dict[str, dict]:
    cfg = run_config(run)
    if cfg.task.name != "peg_insertion_insert":
        raise SystemExit(f"{run} is a run of {cfg.task.name}: the check measured here is peg insertion (insert)'s")
    progress = run_table(run, "progress.csv")
    reset_rb, forward_rb = load_replay(run, "reset"), load_replay(run, "forward")
    for rb, name in ((reset_rb, "reset"), (forward_rb, "forward")):
        if rb.write_count > rb.storage.max_size:
            raise SystemExit(f"{run}: its {name} buffer was filled, its first rows overwritten")
    reset_rows, forward_rows = reset_rb.storage[:reset_rb.write_count], forward_rb.storage[:forward_rb.write_count]
    f0, f1 = rows_at(progress, start, "forward_steps"), rows_at(progress, end, "forward_steps")
    forward_obs = forward_rows["observation"][f0:f1]
    if bool(cfg.reset.get("learn_from_forward", False)):
        window = reset_rows[start:end]
        forward_episodes = torch.unique(forward_rows["collector", "traj_ids"])
        own = ~torch.isin(window["collector", "traj_ids"], forward_episodes)
        reset_obs = window["observation"][own]
    else:
        r0, r1 = rows_at(progress, start, "reset_steps"), rows_at(progress, end, "reset_steps")
        reset_obs = reset_rows["observation"][r0:r1]
    return {"reset": describe(env, reset_obs), "forward": describe(env, forward_obs)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders of peg insertion (insert)")
    parser.add_argument("--start", type=int, default=30000)
    parser.add_argument("--end", type=int, default=50000)
    args = parser.parse_args(argv)
    if not 0 <= args.start < args.end:
        parser.error("--start must be at least 0 and below --end")
    env = PegInsertionEnv("insert")
    print(f"Rows written in {args.start}-{args.end} steps; d_start: the peg's distance from its start "
          f"(inside the check below {CHECK})")
    print("| run | agent | rows | inside the check | d_start, quartiles |")
    print("|---|---|---|---|---|")
    for run in args.runs:
        for agent, row in coverage(env, run, args.start, args.end).items():
            if row["rows"] == 0:
                print(f"| {run} | {agent} | 0 | | |")
                continue
            print(f"| {run} | {agent} | {row['rows']} | {row['inside']:.0%} | "
                  f"{row['q1']:.2f}, {row['median']:.2f}, {row['q3']:.2f} |")


if __name__ == "__main__":
    main()
