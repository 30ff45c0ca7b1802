"""Many seeds of one configuration side by side, then one table and one figure across configurations.

    # seeds 0-9 of one configuration, two processes at a time (Hydra -m, joblib, one torch thread each)
    python recipes/analysis/screen.py run release --seeds 0-9 --jobs 2 -- preset=quick task=ball_in_cup_catch
    python recipes/analysis/screen.py run preact --seeds 0-9 -- preset=quick task=ball_in_cup_catch reset.actor.preact_penalty=0.001
    # the table (screening.md) and the strip plot (screening.png) of every configuration's runs
    python recipes/analysis/screen.py table runs/screening --out results/screening
    # configurations from folders made elsewhere, side by side (each NAME=FOLDER holds seed<k>/ run folders)
    python recipes/analysis/screen.py table --config release=results/table1-peg-insert/peg_insertion_insert/ours \
        --config project=results/reset-actor-paper-sizes/peg_insertion_insert/ours --out <folder>

``run`` puts seed ``k`` of configuration ``NAME`` in ``<root>/NAME/seed<k>`` (``--root``, default
``runs/screening``) with ``resume=auto``: a grid stopped part-way is continued by the same command. ``table``
reads every ``<root>/<name>/seed*/`` that has a ``summary.json``: per seed the manual and episodic resets, the
reset success in the first and in the last quarter, the forward share, the forward return (the mean of the
last quarter's evaluations) and each actor's saturation in the last quarter (the share of action components
beyond +-0.99); across seeds the mean with
a bootstrap 95% interval (``scipy.stats.bootstrap``, BCa, 10,000 resamples, fixed seed); and how many seeds
hold (last-quarter reset success >= 50%).
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

from torchrl_reset_recipes import TRAIN_SCRIPT
from torchrl_reset_recipes.analysis.runs import bootstrap_interval

__all__ = ["seed_list", "named_folders", "seed_runs", "grid_command", "read_seed", "read_configuration",
           "bootstrap_interval", "interval_text", "screening_table", "screening_figure", "HOLDS_AT", "main"]

#: a seed holds when at least this share of its last quarter's reset episodes got back to the start
HOLDS_AT = 0.5
#: the table's columns: summary entry, heading, kind (count, share or number)
COLUMNS = [
    ("manual_resets", "manual resets", "count"),
    ("episodic_resets", "episodic resets", "count"),
    ("success_first", "reset success, first quarter", "share"),
    ("success_last", "reset success, last quarter", "share"),
    ("forward_share", "forward share", "share"),
    ("forward_return", "forward return, last quarter", "number"),
    ("reset_saturation", "reset actor saturation, last quarter", "share"),
    ("forward_saturation", "forward actor saturation, last quarter", "share"),
]


def seed_list(text: str) -> list[int]:
    """``"0-9"`` -> 0..9; ``"0,3,7"`` -> [0, 3, 7]; ``"10-12,15"`` -> [10, 11, 12, 15]."""
    seeds = []
    for part in text.split(","):
        low, _, high = part.strip().partition("-")
        if not low.isdigit() or (high and not high.isdigit()):
            raise ValueError(f"seeds must be numbers or ranges such as 0-9 or 0,3,7; got {text!r}")
        seeds += list(range(int(low), int(high) + 1)) if high else [int(low)]
    return seeds


def named_folders(items: list[str]) -> dict[str, Path]:
    """``["NAME=FOLDER", ...]`` -> ``{NAME: Path(FOLDER)}`` in the order given (each FOLDER holding ``seed<k>/``
    run folders); an item without both parts: ValueError."""
    folders = {}
    for item in items:
        name, _, folder = item.partition("=")
        if not name or not folder:
            raise ValueError(f"configurations are NAME=FOLDER, got {item!r}")
        folders[name] = Path(folder)
    return folders


def seed_runs(items: list[str], seeds: str) -> list[tuple[str, int, Path]]:
    """``(NAME, k, FOLDER/seed<k>)`` for each ``NAME=FOLDER`` of ``items`` and each seed of ``seeds`` (as
    :func:`seed_list` reads it), configuration by configuration; a malformed item or seed list: ValueError."""
    return [(name, seed, folder / f"seed{seed}") for name, folder in named_folders(items).items()
            for seed in seed_list(seeds)]


def grid_command(name: str, seeds: list[int], overrides: list[str], root: str, jobs: int) -> list[str]:
    """The Hydra -m command running ``seeds`` of configuration ``name`` (``jobs`` processes at a time)."""
    if "/" in name or not name:
        raise ValueError(f"a configuration's name is one folder name, got {name!r}")
    return [sys.executable, str(TRAIN_SCRIPT), "-m", *overrides, f"seed={','.join(map(str, seeds))}",
            "threads=1", "progress_bar=false", "resume=auto", f"run_dir={root}/{name}/seed${{seed}}",
            f"hydra.sweep.dir={root}/{name}/multirun", f"hydra.launcher.n_jobs={jobs}"]


def _rows(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _number(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def read_seed(folder: Path) -> dict:
    """One run's screening entries from its ``summary.json`` and ``eval.csv``."""
    summary = json.loads((folder / "summary.json").read_text())
    steps = int(summary["steps"])
    late = [_number(r["forward_return"]) for r in _rows(folder / "eval.csv") if int(r["frames"]) > 0.75 * steps]
    saturation = summary.get("saturation", {}).get("last_quarter", {})
    nan = math.nan
    return {
        "seed": int(summary["seed"]), "steps": steps, "finished": bool(summary.get("finished")),
        "manual_resets": summary["manual_resets"], "episodic_resets": summary["episodic_resets"],
        "success_first": _or_nan(summary.get("reset_success_rate_first_quarter")),
        "success_last": _or_nan(summary.get("reset_success_rate_last_quarter")),
        "forward_share": summary["forward_share"],
        "forward_return": float(np.mean(late)) if late else nan,
        "reset_saturation": _or_nan(saturation.get("reset_saturation")),
        "forward_saturation": _or_nan(saturation.get("forward_saturation")),
    }


def _or_nan(value) -> float:
    return math.nan if value is None else float(value)


def read_configuration(folder: Path) -> list[dict]:
    """Every seed of one configuration that has a summary, by seed."""
    return sorted((read_seed(p) for p in folder.glob("seed*") if (p / "summary.json").exists()),
                  key=lambda row: row["seed"])


def _value(value: float, kind: str) -> str:
    if math.isnan(value):
        return "n/a"
    return f"{100 * value:.0f}%" if kind == "share" else (f"{value:.0f}" if kind == "count" else f"{value:.2f}")


def interval_text(values, kind: str) -> str:
    """The mean of ``values`` with its bootstrap 95% interval, as the table writes it (``kind``: count, share or
    number); the mean alone below three values, ``n/a`` with none."""
    mean, low, high = bootstrap_interval(values)
    if math.isnan(mean):
        return "n/a"
    if math.isnan(low):
        return _value(mean, kind)
    return f"{_value(mean, kind)} [{_value(low, kind)}, {_value(high, kind)}]"


def holds(row: dict) -> bool:
    return not math.isnan(row["success_last"]) and row["success_last"] >= HOLDS_AT


def screening_table(configurations: dict[str, list[dict]]) -> str:
    """Markdown: across seeds per configuration (mean [95% bootstrap interval], seeds that hold), then per seed."""
    heads = [head for _, head, _ in COLUMNS]
    lines = ["| configuration | seeds | seeds that hold | " + " | ".join(heads) + " |",
             "|---|---|---|" + "---|" * len(heads)]
    for name, rows in configurations.items():
        cells = [interval_text([_number(r[key]) for r in rows], kind) for key, _, kind in COLUMNS]
        seeds = ",".join(str(r["seed"]) for r in rows)
        lines.append(f"| {name} | {len(rows)} ({seeds}) | {sum(map(holds, rows))} of {len(rows)} | "
                     + " | ".join(cells) + " |")
    lines += ["", f"Mean [bootstrap 95% interval] over the seeds (BCa, 10,000 resamples; none below three seeds). "
              f"A seed holds when at least {HOLDS_AT:.0%} of its last quarter's reset episodes got back to the start.",
              "", "| configuration | seed | steps | holds | " + " | ".join(heads) + " |",
              "|---|---|---|---|" + "---|" * len(heads)]
    for name, rows in configurations.items():
        for r in rows:
            steps = f"{r['steps']}" + ("" if r["finished"] else " (stopped)")
            lines.append(f"| {name} | {r['seed']} | {steps} | {'yes' if holds(r) else 'no'} | "
                         + " | ".join(_value(_number(r[key]), kind) for key, _, kind in COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def screening_figure(configurations: dict[str, list[dict]]):
    """Strip plots, configurations side by side: each seed a dot, the mean and its 95% interval a bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("manual_resets", "manual resets", 1.0), ("success_last", "reset success, last quarter (%)", 100.0),
              ("forward_share", "forward share (%)", 100.0), ("reset_saturation", "reset actor saturation (%)", 100.0)]
    names = list(configurations)
    fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 3.8), squeeze=False)
    jitter = np.random.default_rng(0)
    for ax, (key, label, scale) in zip(axes[0], panels):
        for i, name in enumerate(names):
            values = np.array([_number(r[key]) for r in configurations[name]]) * scale
            shown = values[~np.isnan(values)]
            ax.scatter(i + jitter.uniform(-0.15, 0.15, shown.size), shown, s=14, alpha=0.7, color=f"C{i % 10}")
            mean, low, high = bootstrap_interval(list(values))
            if not math.isnan(mean):
                ax.hlines(mean, i - 0.3, i + 0.3, color="black")
            if not math.isnan(low):
                ax.vlines(i + 0.35, low, high, color="black")
        if key == "success_last":
            ax.axhline(100 * HOLDS_AT, color="grey", linestyle=":", linewidth=1)
        ax.set_xticks(range(len(names)), names, rotation=30, ha="right")
        ax.set_title(label, fontsize=10)
    fig.suptitle("Screening: each seed a dot; the mean (line) and its bootstrap 95% interval (bar)")
    fig.tight_layout()
    return fig


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run seeds of one configuration (Hydra -m, joblib)")
    run.add_argument("name", help="the configuration's name (its folder under --root)")
    run.add_argument("--seeds", default="0-9", help="seeds: a range 0-9 or a list 0,3,7 (default 0-9)")
    run.add_argument("--jobs", type=int, default=2, help="processes at a time (default 2; at most the cores)")
    run.add_argument("--root", default="runs/screening", help="where the runs go (default runs/screening)")
    run.add_argument("overrides", nargs="*", help="the recipe's overrides (after --)")
    table = sub.add_parser("table", help="the table and figure of every configuration under a folder")
    table.add_argument("root", type=Path, nargs="?", default=None, help="the folder holding <name>/seed<k>/ run folders")
    table.add_argument("--config", action="append", default=[], metavar="NAME=FOLDER",
                       help="a configuration by its own folder of seed<k>/ run folders, instead of or beside root's "
                            "(repeat it: folders of runs made elsewhere side by side, such as two results folders)")
    table.add_argument("--out", type=Path, default=None, help="where screening.md and screening.png go (default: root)")
    table.add_argument("--order", default=None, help="the configurations' order, comma-separated (default: by name)")
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []  # the recipe's overrides, after --
    args = parser.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    if args.command == "run":
        args.overrides = [*args.overrides, *extra]
        if args.jobs < 1:
            parser.error("--jobs must be at least 1")
        command = grid_command(args.name, seed_list(args.seeds), args.overrides, args.root, args.jobs)
        print(" ".join(command), flush=True)
        sys.exit(subprocess.call(command))
    folders = {p.name: p for p in sorted(args.root.iterdir()) if p.is_dir()} if args.root else {}
    try:
        folders.update(named_folders(args.config))
    except ValueError as err:
        parser.error(f"--config: {err}")
    if not folders:
        parser.error("give a root folder or at least one --config NAME=FOLDER")
    if args.out is None and args.root is None:
        parser.error("--out is needed without a root folder")
    names = args.order.split(",") if args.order else list(folders)
    unknown = [name for name in names if name not in folders]
    if unknown:
        parser.error(f"--order names {unknown}, which are not among the configurations {list(folders)}")
    configurations = {name: rows for name in names if (rows := read_configuration(folders[name]))}
    if not configurations:
        raise SystemExit(f"no run folder with a summary.json under {', '.join(map(str, folders.values()))} (seed*/)")
    out = args.out or args.root
    out.mkdir(parents=True, exist_ok=True)
    (out / "screening.md").write_text(screening_table(configurations))
    screening_figure(configurations).savefig(out / "screening.png", dpi=120)
    print(f"wrote {out / 'screening.md'} and {out / 'screening.png'}")


if __name__ == "__main__":
    main()
