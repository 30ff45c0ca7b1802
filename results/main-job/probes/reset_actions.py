"""Frozen: its question is decided. It last ran at commit 271779f, as results/quick-ball-in-cup/probes/reset_actions.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/quick-ball-in-cup/probes/reset_actions.py --help``.

The reset agent's last actions, from a run's checkpoint: does the reset policy sit at the action bound?

    python results/main-job/probes/reset_actions.py <run folder> [<run folder> ...] [--last 2000]

Reads the newest checkpoint's reset replay buffer (the actions as executed by the reset policy with its
exploration noise; with ``exploration.clip: false`` as drawn, so they may lie outside the action box) and
prints, over its last ``--last`` rows: the mean of |a|, the share of action entries outside [-1, 1], and
each action dimension's mean and standard deviation.
"""
import argparse
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
from torchrl_reset_recipes.analysis.saved_runs import latest_checkpoint, load_replay


def reset_actions(run: Path, last: int):
    """The newest checkpoint's name and the last ``last`` actions of its reset replay buffer."""
    folder = latest_checkpoint(run)
    reset_rb = load_replay(run, "reset", checkpoint=folder)
    return folder.name, reset_rb[:]["action"][-last:]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run folders written by recipes/train.py")
    parser.add_argument("--last", type=int, default=2000, help="the newest reset actions to read")
    args = parser.parse_args()
    for run in args.runs:
        step, a = reset_actions(run, args.last)
        means = ", ".join(f"{v:+.2f}" for v in a.mean(0).tolist())
        stds = ", ".join(f"{v:.2f}" for v in a.std(0).tolist())
        print(f"{run} ({step}, last {len(a)} reset actions): mean |a| {a.abs().mean():.2f}; "
              f"outside [-1, 1] {100 * (a.abs() > 1).float().mean():.0f}%; mean ({means}); sd ({stds})")


if __name__ == "__main__":
    main()
