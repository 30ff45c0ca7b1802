"""Frozen: its question is decided. It last ran at commit 271779f, as results/100000-tier2/probes/trigger_states.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/100000-tier2/probes/trigger_states.py --help``.

Where a cliff-cheetah run's steps went, and what the states before its triggers look like, from its files.

    python results/table1-cliff-cheetah/probes/trigger_states.py results/table1-cliff-cheetah/cliff_cheetah/ours/seed0

Reads ``resets.csv`` and ``triggers.csv`` only (no model): the steps spent in reset episodes that
succeeded and in those that ran out (each a manual reset), how many triggers came within the forward
episode's first two steps and how fast the body moved there (the norm of qvel, all nine joints, against
about 0.3 for the task's start noise), and the state before each trigger split by the outcome of the
reset episode that followed it (paired by its start, ``frames - steps``): |pitch| and pitch rate.
"""
from __future__ import annotations

import argparse
import math
import statistics
from pathlib import Path

from torchrl_reset_recipes.analysis.saved_runs import run_table
from torchrl_reset_recipes.analysis.stretches import keyed_by_start

NQ = 9  # cliff-cheetah: qpos (9) then qvel (9)


def quartiles(values) -> str:
    values = list(values)
    if len(values) < 2:
        return " ".join(f"{v:.2f}" for v in values) or "-"
    return " / ".join(f"{v:.2f}" for v in statistics.quantiles(values, n=4))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", type=Path, nargs="+", help="cliff-cheetah run folders written by recipes/train.py")
    args = parser.parse_args(argv)
    for run in args.runs:
        resets, triggers = run_table(run, "resets.csv"), run_table(run, "triggers.csv")
        print(f"{run} (to frame {resets[-1]['frames'] if resets else 0})")
        for outcome in ("success", "manual"):
            chosen = [int(r["steps"]) for r in resets if r["outcome"] == outcome]
            print(f"  reset episodes, {outcome}: {len(chosen)}, {sum(chosen):,} steps")
        states = [[float(v) for v in t["observation"].split()] for t in triggers]
        steps = [int(t["steps"]) for t in triggers]
        speed = [math.sqrt(sum(v * v for v in s[NQ:])) for s in states]
        early = [v for v, k in zip(speed, steps) if k <= 2]
        print(f"  triggers: {len(triggers)}; within the first 2 forward steps: {len(early)}; |qvel| quartiles there "
              f"{quartiles(early)}, at all triggers {quartiles(speed)}")
        after = keyed_by_start(resets)
        for outcome in ("success", "manual"):
            chosen = [s for s, t in zip(states, triggers) if after.get(int(t["frames"]), {}).get("outcome") == outcome]
            print(f"  before a reset that ended in {outcome} ({len(chosen)}): |pitch| quartiles "
                  f"{quartiles(abs(s[2]) for s in chosen)}, pitch rate quartiles {quartiles(s[NQ + 2] for s in chosen)}")


if __name__ == "__main__":
    main()
