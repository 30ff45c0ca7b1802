"""The protocol's rule (README.md, fixed before the runs), applied to the run folders here.

    python results/table1-four-tasks/verdicts.py            # this folder: <task>/<algo>/seed<k>/summary.json

Per task: each seed of ours passes when its last quarter's reset success is at least 80% and its manual resets
are at most half the episodic agent's; the task **works** when seeds 0, 1 and 2 of ours all pass, and does not
once one fails (with fewer in and none failed: not decided). Then ours' mean manual resets against LNT's over the
seeds both have, each with its bootstrap 95% interval (screen.py's: BCa, 10,000 resamples; none below three seeds), and which
order holds. The forward actor's saturation in the last quarter is shown beside each seed of ours.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from torchrl_reset_recipes.analysis.screen import interval_text, read_configuration

TASKS = ["ball_in_cup_catch", "ball_in_cup_throw", "peg_insertion_remove", "cliff_walker"]
SEEDS = (0, 1, 2)
SUCCESS_AT = 0.80


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


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, nargs="?", default=Path(__file__).resolve().parent)
    args = parser.parse_args(argv)
    for task in TASKS:
        print("\n".join(task_verdict(args.folder, task)))


if __name__ == "__main__":
    main()
