"""The protocol's rule (README.md, fixed before the runs), applied to the run folders here.

    python results/table1-four-tasks/verdicts.py            # this folder: <task>/<algo>/seed<k>/summary.json

Per task: each seed of ours passes when its last quarter's reset success is at least 80% and its manual resets
are at most half the episodic agent's; the task **works** when seeds 0, 1 and 2 of ours all pass, and does not
once one fails (with fewer in and none failed: not decided). Then ours' mean manual resets against LNT's over the
seeds both have, each with its bootstrap 95% interval (screen.py's: BCa, 10,000 resamples; none below three seeds), and which
order holds. The forward actor's saturation in the last quarter is shown beside each seed of ours.

    python results/table1-four-tasks/verdicts.py --rows     # the Table 1 rows of results/README.md and README.md

``--rows`` prints one Markdown row per task, as the two READMEs' Table 1 has them: manual resets at 100k of ours,
ours with the paper's reset actor, LNT and LNT-sparse, each the mean over seeds 0-2 with its bootstrap 95% interval
(all three in), or each seed's count while fewer are in; the paper's ours / LNT / LNT-sparse; the task's Fig. 3.
Links are relative to ``--link-base`` (default: results/README.md's).
"""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

from torchrl_reset_recipes.analysis.runs import PAPER_TABLE1, TASK_TITLES
from torchrl_reset_recipes.analysis.screen import interval_text, read_configuration

TASKS = ["ball_in_cup_catch", "ball_in_cup_throw", "peg_insertion_remove", "cliff_walker"]
SEEDS = (0, 1, 2)
SUCCESS_AT = 0.80
#: the Table 1 columns: (run folder name, what the README calls it)
COLUMNS = (("ours", "ours"), ("ours_release_actor", "ours, paper's actor"), ("lnt", "LNT"), ("lnt_sparse", "LNT-sparse"))


def passes(row: dict) -> bool:
    return (not math.isnan(row["success_last"]) and row["success_last"] >= SUCCESS_AT
            and row["manual_resets"] <= row["episodic_resets"] / 2)


def task_verdict(folder: Path, task: str) -> list[str]:
    ours = {r["seed"]: r for r in read_configuration(folder / task / "ours") if r["finished"] and r["seed"] in SEEDS}
    lnt = {r["seed"]: r for r in read_configuration(folder / task / "lnt") if r["finished"] and r["seed"] in SEEDS}
    lines = [f"### {task}", ""]
    for seed, r in sorted(ours.items()):
        lines.append(f"- ours seed {seed}: last quarter {r['success_last']:.0%} successful, {r['manual_resets']} manual "
                     f"against {r['episodic_resets']} episodic: {'passes' if passes(r) else 'fails'} (forward actor "
                     f"saturation {r['forward_saturation']:.0%})")
    passed = sum(passes(r) for r in ours.values())
    if passed < len(ours):  # one failing seed decides it, whatever the others do
        lines.append(f"- **does not work**: {len(ours) - passed} of the {len(ours)} seeds in fail")
    elif len(ours) == len(SEEDS):
        lines.append(f"- **works**: {passed} of {len(SEEDS)} seeds pass")
    else:
        lines.append(f"- not decided: {passed} of {len(ours)} seeds in pass ({len(SEEDS) - len(ours)} not in)")
    both = sorted(set(ours) & set(lnt))
    if both:
        a = [float(ours[s]["manual_resets"]) for s in both]
        b = [float(lnt[s]["manual_resets"]) for s in both]
        order = "ours below LNT" if sum(a) < sum(b) else "LNT at or below ours"
        lines.append(f"- manual resets on seeds {','.join(map(str, both))}: ours {interval_text(a, 'count')}, "
                     f"LNT {interval_text(b, 'count')}: {order}")
    else:
        lines.append("- ours against LNT: no seed has both yet")
    return lines + [""]


def manual_resets_cell(folder: Path) -> str:
    """One configuration's manual resets: the mean [95% interval] over seeds 0-2 once all three finished, each
    finished seed's count before (``seeds 0, 1: 350, 3``), empty with none."""
    done = {r["seed"]: r["manual_resets"] for r in read_configuration(folder) if r["finished"] and r["seed"] in SEEDS}
    if len(done) == len(SEEDS):
        return interval_text([float(done[s]) for s in SEEDS], "count")
    if not done:
        return ""
    seeds = sorted(done)
    return f"seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}: {', '.join(str(done[s]) for s in seeds)}"


def table_rows(folder: Path, link_base: Path) -> list[str]:
    """The Table 1 rows of the four tasks, links relative to ``link_base``."""
    rows = []
    for task in TASKS:
        cells = [manual_resets_cell(folder / task / name) for name, _ in COLUMNS]
        paper = " / ".join(str(PAPER_TABLE1[(task, algo)][1]) for algo in ("ours", "lnt", "lnt_sparse"))
        fig = folder / "report" / f"fig3_{task}.png"
        link = f"[png]({Path(os.path.relpath(fig, link_base)).as_posix()})" if fig.exists() else ""
        rows.append(f"| {TASK_TITLES[task]} | " + " | ".join(cells) + f" | {paper} | {link} |")
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, nargs="?", default=Path(__file__).resolve().parent)
    parser.add_argument("--rows", action="store_true", help="print the four tasks' Table 1 rows instead")
    parser.add_argument("--link-base", type=Path, default=None,
                        help="the folder the rows' links start from (default: the folder above FOLDER)")
    args = parser.parse_args(argv)
    if not args.folder.is_dir():
        parser.error(f"{args.folder} is no folder")
    if args.rows:
        header = "| task | " + " | ".join(title for _, title in COLUMNS) + " | the paper: ours / LNT / LNT-sparse | Fig. 3 |"
        print("\n".join([header, "|---" * (len(COLUMNS) + 3) + "|"]
                        + table_rows(args.folder, args.link_base or args.folder.resolve().parent)))
        return
    for task in TASKS:
        print("\n".join(task_verdict(args.folder, task)))


if __name__ == "__main__":
    main()
