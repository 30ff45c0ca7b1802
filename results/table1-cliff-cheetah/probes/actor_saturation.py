"""Frozen: its question is decided. It last ran at commit 271779f, as results/100000-tier2/probes/actor_saturation.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/100000-tier2/probes/actor_saturation.py --help``.

How a run's reset actor saturates over training: its outputs before the tanh, checkpoint by checkpoint.

    python results/table1-cliff-cheetah/probes/actor_saturation.py runs/tier2/cliff_cheetah/ours/seed2 \\
        --checkpoints runs/tier2/archive/ours/seed2 --out saturation_ours_seed2

A run keeps only its last two checkpoints; ``--checkpoints`` names a folder of kept ``step_*/state.pt``
(default: the run's ``checkpoints/kept``, written with ``keep_states_every``, or else its ``checkpoints``). On one fixed set of states, ``--states`` trigger states
drawn evenly from the run's whole ``triggers.csv`` (the states the reset actor starts from), each
checkpoint's reset actor (no exploration) gives: the median |output before the tanh| per motor, the
share of action components beyond +-0.99 (where tanh' < 0.02: the actor's gradient to that output is
all but gone), how many distinct corners (sign patterns) it commands and the share of states given the
most common one. Beside them, from ``resets.csv``, the share of the reset episodes that ended in the
checkpoint's stretch (since the checkpoint before it) that succeeded. Writes ``<out>.csv`` and
``<out>.png`` (saturated share and reset success against steps).
"""
from __future__ import annotations

import argparse
import csv
from collections import Counter
from pathlib import Path

import torch
from tensordict import TensorDict

ROOT = Path(__file__).resolve().parents[3]

from torchrl_reset_recipes.training.checkpoints import checkpoint_step
from torchrl_reset_recipes.analysis.saved_runs import load_agents, logged_observations, run_config, run_table


def fixed_states(run: Path, count: int) -> torch.Tensor:
    """``count`` trigger states drawn evenly over the run's ``triggers.csv`` (all of them if fewer)."""
    rows = run_table(run, "triggers.csv")
    if not rows:
        raise SystemExit(f"{run} has no trigger states (triggers.csv is empty or absent)")
    picks = range(len(rows)) if count >= len(rows) else [i * len(rows) // count for i in range(count)]
    return logged_observations([rows[i] for i in picks])


def success_by_stretch(run: Path, steps: list[int], first: int) -> list[tuple[int, int]]:
    """(successful, ended) reset episodes in each stretch (previous step, step], the first from ``first``."""
    resets = [(int(r["frames"]), r["outcome"] == "success") for r in run_table(run, "resets.csv")]
    out, before = [], first
    for step in steps:
        here = [ok for frames, ok in resets if before < frames <= step]
        out.append((sum(here), len(here)))
        before = step
    return out


def saturation(actor, states: torch.Tensor) -> dict:
    with torch.no_grad():
        acted = actor(TensorDict(observation=states, batch_size=[len(states)]))
    pre, action = acted["action_preactivation"], acted["action"]
    corners = Counter(tuple(row) for row in torch.sign(action).int().tolist())
    corner, held = corners.most_common(1)[0]
    return {"pre_tanh_median": [round(float(v), 2) for v in pre.abs().median(0).values],
            "saturated": float((action.abs() > 0.99).float().mean()),
            "corners": len(corners), "top_corner": corner, "top_corner_share": held / len(states)}


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a run folder written by recipes/train.py")
    parser.add_argument("--checkpoints", type=Path, default=None,
                        help="a folder of step_*/state.pt (default: the run's checkpoints/kept, else its checkpoints)")
    parser.add_argument("--states", type=int, default=200, help="trigger states in the fixed set")
    parser.add_argument("--out", type=Path, default=None, help="writes <out>.csv and <out>.png")
    args = parser.parse_args(argv)
    if args.states < 1:
        parser.error("--states must be positive")
    torch.set_num_threads(1)
    folder = args.checkpoints or next((f for f in (args.run / "checkpoints" / "kept", args.run / "checkpoints")
                                       if f.is_dir()), args.run / "checkpoints")
    found = sorted((s, p) for p in folder.glob("step_*") if (s := checkpoint_step(p)) is not None
                   and (p / "state.pt").exists())
    if not found:
        raise SystemExit(f"{folder} holds no step_*/state.pt")
    states = fixed_states(args.run, args.states)
    # the first stretch as long as those between the states found (kept every so many steps, or checkpoints)
    every = found[1][0] - found[0][0] if len(found) > 1 else int(run_config(args.run).checkpoint_every)
    successes = success_by_stretch(args.run, [s for s, _ in found], first=max(0, found[0][0] - every))
    print(f"{args.run}: {len(found)} checkpoints, {len(states)} fixed trigger states")
    print("step | median |pre-tanh| per motor | |a| > 0.99 | corners | most common corner (share) | resets since the last checkpoint: successful / ended")
    rows = []
    for (step, path), (ok, ended) in zip(found, successes):
        row = {"step": step, **saturation(load_agents(args.run, checkpoint=path, agents=("reset",)).reset.actor.eval(), states),
               "resets_successful": ok, "resets_ended": ended}
        rows.append(row)
        print(f"{step} | {' '.join(f'{v:.1f}' for v in row['pre_tanh_median'])} | {row['saturated']:.0%} | {row['corners']} | "
              f"{row['top_corner']} ({row['top_corner_share']:.0%}) | {ok} / {ended}")
    if args.out is not None:
        write(rows, args.out, args.run)
    return rows


def write(rows: list[dict], out: Path, run: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.with_suffix(".csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        for row in rows:
            writer.writerow({**row, "pre_tanh_median": " ".join(map(str, row["pre_tanh_median"])),
                             "top_corner": " ".join(map(str, row["top_corner"]))})
    steps = [r["step"] for r in rows]
    fig, ax = plt.subplots(figsize=(7, 3.2))
    ax.plot(steps, [100 * r["saturated"] for r in rows], "o-", label="action components beyond +-0.99 (%)")
    ax.plot(steps, [100 * r["top_corner_share"] for r in rows], "s--", label="states given the most common corner (%)")
    rate = [(s, 100 * r["resets_successful"] / r["resets_ended"]) for s, r in zip(steps, rows) if r["resets_ended"]]
    ax.plot([s for s, _ in rate], [v for _, v in rate], "^:", label="reset episodes that succeeded, since the last checkpoint (%)")
    ax.set_xlabel("steps (forward + reset)")
    ax.set_ylim(-3, 103)
    ax.set_title(f"{run.parent.name} {run.name}: the reset actor's saturation", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=110)
    plt.close(fig)
    print(f"wrote {out.with_suffix('.csv')} and {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
