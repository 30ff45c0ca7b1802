"""Tier 1 at the release's settings against tier 1 before them: triggers, forward share and reset success
by stretch of training, per seed, from the run folders' files.

    python results/100000-release/probes/compare.py --new runs/release/peg_insertion_insert/ours \\
        --old results/100000/peg_insertion_insert/ours --seeds 0 1 --upto 30000 --window 10000

For each run and each ``--window``-step stretch up to ``--upto``: triggered resets, forward episodes,
forward share (from progress.csv), reset episodes, successful ones and manual resets (from resets.csv).
"""
import argparse
import csv
from pathlib import Path


def rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def at(progress: list[dict], frames: int) -> dict:
    """The progress row at ``frames`` (the last one logged at or before it)."""
    before = [r for r in progress if int(r["frames"]) <= frames]
    return before[-1] if before else {k: 0 for k in progress[0]}


def stretches(run: Path, upto: int, window: int) -> list[dict]:
    progress, resets = rows(run / "progress.csv"), rows(run / "resets.csv")
    triggers = rows(run / "triggers.csv")
    out = []
    for start in range(0, upto, window):
        end = start + window
        a, b = at(progress, start), at(progress, end)
        if int(b["frames"]) < end:
            break
        fwd = int(b["forward_steps"]) - int(a["forward_steps"])
        episodes = [r for r in resets if start < int(r["frames"]) <= end]
        success = sum(r["outcome"] == "success" for r in episodes)
        out.append({
            "steps": f"{start // 1000}-{end // 1000}k",
            "triggers": sum(start < int(r["frames"]) <= end for r in triggers),
            "forward episodes": int(b["forward_episodes"]) - int(a["forward_episodes"]),
            "forward share": f"{fwd / window:.3f}",
            "reset episodes": len(episodes),
            "successful": success,
            "manual": len(episodes) - success,
            "success rate": f"{success / len(episodes):.0%}" if episodes else "n/a",
        })
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--new", required=True, help="folder holding seed<k>/ of the runs at the release's settings")
    parser.add_argument("--old", required=True, help="folder holding seed<k>/ of the earlier runs")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--upto", type=int, default=30000)
    parser.add_argument("--window", type=int, default=10000)
    args = parser.parse_args()
    for seed in args.seeds:
        for label, folder in (("release's settings", args.new), ("before", args.old)):
            table = stretches(Path(folder) / f"seed{seed}", args.upto, args.window)
            print(f"\nseed {seed}, {label} ({folder}/seed{seed})\n")
            if not table:
                print("(not there yet)")
                continue
            print("| " + " | ".join(table[0]) + " |")
            print("|" + "---|" * len(table[0]))
            for r in table:
                print("| " + " | ".join(str(v) for v in r.values()) + " |")


if __name__ == "__main__":
    main()
