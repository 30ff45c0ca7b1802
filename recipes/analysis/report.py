"""Turn training runs into the paper's Table 1 and Figures 3, 4 and 5.

    python recipes/analysis/report.py runs/                      # every run under runs/
    python recipes/analysis/report.py runs/cliff_cheetah --out report/
    python recipes/analysis/report.py runs/ --budget 100000        # every run as it stood at 100k steps

Reads every folder holding a ``summary.json`` written by ``train.py`` (any mix of tasks, algorithms,
seeds and p_thresh values) and writes into ``--out`` (default ``<first folder>/report``). Runs of one
task and algorithm that ran with different settings (anything in their ``config.yaml`` but the seed,
the length, where and how fast they ran and what they logged) are kept apart, labelled with what they
changed (``ours (algo.initial_logit_bias=-4)`` beside ``ours (paper's setting)``), never averaged together:

    python recipes/analysis/report.py runs/paper runs/options/initial_logit_bias-4 --budget 100000

A key that an older run's ``config.yaml`` lacks is read as what its absence meant when the run ran
(``training/absent_keys.py``), not as today's default. ``NAME=PATH`` names the runs under ``PATH``: they are one
setting, labelled ``NAME`` (runs of two versions of the code side by side, which may differ in more
than their configs), and ``table1.md`` lists what each named folder set apart from the paper preset:

    python recipes/analysis/report.py tier1=results/100000 release=results/table1-peg-insert --budget 100000

- ``table1.md``: per task and algorithm, the mean and standard deviation over seeds of the average
  forward return, manual resets, forward share and reset success rate, beside the paper's numbers;
- ``fig3_<task>.png``: evaluation forward return and cumulative manual resets against steps, each algorithm's
  manual resets beside the resets an episodic agent would have needed (one per forward episode, dashed); a
  note on the return panel where a group has no evaluation yet or returned 0 at every one;
- ``fig4_<task>_<algo>.png``: the same four metrics against p_thresh (when runs differ in p_thresh);
- ``fig5_<task>_<algo>.png``: the curriculum, the state just before each triggered reset against steps (for
  a run without a triggered reset, a figure that says so);
- ``diagnostics_<task>_<algo>.png``: the trigger's scores against its threshold (ours: p and p_thresh; LNT:
  the reset Q-ensemble's minimum Q and Q_thresh), the reset model on examples, replay and forward states, the
  reset success rate per stretch of the run and how far reset episodes ended from the start, by outcome.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from torchrl_reset_recipes.analysis.figures import (figure3, figure4, figure5, figure_diagnostics)
from torchrl_reset_recipes.analysis.runs import (PAPER_TABLE1, TASK_TITLES, METRICS, RunFolder, named_settings,
                                                 is_paper_setting,
                                                 title, find_runs,
                                                 mean_std, reached,
                                                 complete,
                                                 row_order, by)


def _cell(mean: float, std: float, low: float = math.nan, high: float = math.nan, *, kind: str) -> str:
    if math.isnan(mean):
        return "n/a"
    if kind == "share":
        text, interval = f"{100 * mean:.1f}% ± {100 * std:.1f}", f" [{100 * low:.1f}, {100 * high:.1f}]"
    elif kind == "count":
        text, interval = f"{mean:.0f} ± {std:.0f}", f" [{low:.0f}, {high:.0f}]"
    else:
        text, interval = f"{mean:.2f} ± {std:.2f}", f" [{low:.2f}, {high:.2f}]"
    return text if math.isnan(low) else text + interval


def _paper(value, kind: str) -> str:
    return f"{100 * value:.1f}%" if kind == "share" else (f"{value:.0f}" if kind == "count" else f"{value:.2f}")


def table1(runs: list[RunFolder]) -> str:
    """Markdown table: one row per (task, algo, setting, p_thresh) group, mean ± std over its seeds, paper beside
    (the paper's numbers only on its own setting's rows)."""
    groups, short = complete(by(runs, "task", "algo", "setting", "p_thresh"))
    kinds = ("return", "count", "share", "share")
    lines = [
        "| task | algo | p_thresh | seeds | steps | avg return | manual resets | forward share | success rate |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for (task, algo, setting, p_thresh), members in sorted(groups.items(), key=lambda kv: row_order(*kv[0])):
        paper = PAPER_TABLE1.get((task, algo)) if is_paper_setting(setting) else None
        cells = []
        for metric, kind, index in zip(METRICS, kinds, range(4)):
            cell = _cell(*mean_std([r.summary[metric] for r in members]), kind=kind)
            if paper is not None:
                cell += f" (paper {_paper(paper[index], kind)})"
            cells.append(cell)
        steps = "/".join(map(str, sorted({r.summary.get("steps") for r in members})))
        if not all(reached(r) for r in members):
            steps += " (in progress)"
        lines.append(
            f"| {TASK_TITLES.get(task, task)} | {title(algo, setting)} | {p_thresh} | {len(members)} | "
            f"{steps} | " + " | ".join(cells) + " |"
        )
    budget = {r.budget for r in runs} - {None}
    note = f" at a budget of {budget.pop()} steps" if budget else ""
    lines += [
        "",
        f"Mean ± standard deviation over seeds (population form: divided by the number of seeds){note}, and over three "
        "or more seeds the mean's bootstrap 95% interval in brackets (BCa, 10,000 resamples); the paper's numbers "
        "are 1.5M-step means of 5 seeds.",
    ]
    named = named_settings(runs)
    if named:
        lines += ["", "What each named folder's runs set apart from the paper preset in their config.yaml (the recipe's "
                  "defaults; a key an older config lacks read as what its absence meant then). What changed in the code "
                  "without a key, such as a task's model, is not listed: each run's code.jsonl names its commits.",
                  *named]
    if short:
        lines.append("Left out of the means, still short of the budget: " + "; ".join(
            f"{title(r.algo, r.setting)} seed {r.summary['seed']} at {r.summary.get('steps')} steps"
            for r in sorted(short, key=lambda r: (r.algo, r.setting, r.summary["seed"]))) + ".")
    lines += [
        "",
        "| task | algo | p_thresh | seeds | manual resets | episodic resets | saved | release's baseline "
        "| saved | manual resets per 1k steps, last quarter |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for (task, algo, setting, p_thresh), members in sorted(groups.items(), key=lambda kv: row_order(*kv[0])):
        manual = mean_std([r.summary["manual_resets"] for r in members])
        episodic = mean_std([r.summary["episodic_resets"] for r in members])
        saved = mean_std([r.summary["episodic_resets"] - r.summary["manual_resets"] for r in members])
        late = mean_std([r.summary["late_manual_rate"] for r in members])
        by_steps = mean_std([r.summary["baseline_hard_resets"] for r in members])
        saved_by_steps = mean_std([r.summary["baseline_hard_resets"] - r.summary["manual_resets"] for r in members])
        lines.append(
            f"| {TASK_TITLES.get(task, task)} | {title(algo, setting)} | {p_thresh} | {len(members)} | "
            f"{_cell(*manual, kind='count')} | {_cell(*episodic, kind='count')} | {_cell(*saved, kind='count')} | "
            f"{_cell(*by_steps, kind='count')} | {_cell(*saved_by_steps, kind='count')} | {_cell(*late, kind='return')} |"
        )
    return "\n".join(lines) + (
        "\n\nEpisodic resets: the resets an agent without a reset agent would have needed, one per forward "
        "episode (the optimistic baseline the authors' release names). Release's baseline: the count the "
        "release logs as its baseline, one hard reset per H_f calls of the forward agent's step (triggered "
        "calls included), what an episodic agent taking those steps in full H_f-step episodes would need; "
        "it is lower where the trigger cuts episodes short.\n"
    )



def report(paths: list[Path], out: Path | None = None, budget: int | None = None,
           names: dict[Path, str] | None = None) -> dict[str, list[Path]]:
    runs = find_runs(paths, budget, names)
    out = Path(out) if out is not None else (paths[0] if paths[0].is_dir() else paths[0].parent) / "report"
    out.mkdir(parents=True, exist_ok=True)
    table_path = out / "table1.md"
    table_path.write_text(table1(runs))
    return {"table": [table_path], "fig3": figure3(runs, out), "fig4": figure4(runs, out), "fig5": figure5(runs, out),
            "diagnostics": figure_diagnostics(runs, out)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="+", type=str,
                        help="run folders, or folders holding run folders; NAME=PATH names the runs under PATH "
                             "(one setting, labelled NAME; table1.md lists what it set apart from the paper preset)")
    parser.add_argument("--out", type=Path, default=None, help="where to write (default: <first path>/report)")
    parser.add_argument("--budget", type=int, default=None,
                        help="compare every run as it stood at this many steps (default: at its end)")
    args = parser.parse_args(argv)
    if args.budget is not None and args.budget < 1:
        parser.error(f"--budget must be a positive number of steps, got {args.budget}")
    paths, names = [], {}
    for given in args.paths:
        name, sep, rest = given.partition("=")
        if sep and name and "/" not in name and not Path(given).exists():
            if not rest:
                parser.error(f"{given!r}: NAME=PATH needs a path after '='")
            paths.append(Path(rest))
            names[Path(rest)] = name
        else:
            paths.append(Path(given))
    for path in paths:
        if not path.exists():
            parser.error(f"{path} does not exist")
    written = report(paths, args.out, args.budget, names)
    print(Path(written["table"][0]).read_text())
    for kind in ("fig3", "fig4", "fig5", "diagnostics"):
        for path in written[kind]:
            print(f"wrote {path}")


if __name__ == "__main__":
    main()
