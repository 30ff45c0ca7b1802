"""Frozen: its question is decided. It last ran at commit 271779f, as results/100000-release/probes/compare.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/100000-release/probes/compare.py --help``.

Tier 1 at the release's settings against tier 1 before them: triggers, forward share and reset success
by stretch of training, per seed, from the run folders' files.

    python results/table1-peg-insert/probes/compare.py --new runs/release/peg_insertion_insert/ours \\
        --old results/100000/peg_insertion_insert/ours --seeds 0 1 --upto 30000 --window 10000

For each seed, the two runs' stretch tables side by side, as ``recipes/analysis/stretches.py`` makes them (its
columns: triggered resets, forward episodes, forward share, reset episodes, successful ones, manual
resets, the success rate).
"""
import argparse
from pathlib import Path

from torchrl_reset_recipes.analysis.stretches import markdown, stretches


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--new", required=True, help="folder holding seed<k>/ of the runs at the release's settings")
    parser.add_argument("--old", required=True, help="folder holding seed<k>/ of the earlier runs")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--upto", type=int, default=30000)
    parser.add_argument("--window", type=int, default=10000)
    args = parser.parse_args()
    for seed in args.seeds:
        for label, folder in (("release's settings", args.new), ("before", args.old)):
            run = Path(folder) / f"seed{seed}"
            print(f"\nseed {seed}, {label} ({run})\n")
            print(markdown(stretches(run, args.window, args.upto)) if (run / "progress.csv").exists()
                  else "(not there yet)")


if __name__ == "__main__":
    main()
