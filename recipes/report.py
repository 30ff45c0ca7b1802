"""Turn training runs into the paper's Table 1 and Figures 3, 4 and 5.

    python recipes/report.py runs/                      # every run under runs/
    python recipes/report.py runs/cliff_cheetah --out report/
    python recipes/report.py runs/ --budget 100000        # every run as it stood at 100k steps

Reads every folder holding a ``summary.json`` written by ``train.py`` (any mix of tasks, algorithms,
seeds and p_thresh values) and writes into ``--out`` (default ``<first folder>/report``). Runs of one
task and algorithm that ran with different settings (anything in their ``config.yaml`` but the seed,
the length, where and how fast they ran and what they logged) are kept apart, labelled with what they
changed (``ours (algo.initial_logit_bias=-4)`` beside ``ours (paper's setting)``), never averaged together:

    python recipes/report.py runs/paper runs/options/initial_logit_bias-4 --budget 100000

A key that an older run's ``config.yaml`` lacks is read as what its absence meant when the run ran
(``absent_keys.py``), not as today's default. ``NAME=PATH`` names the runs under ``PATH``: they are one
setting, labelled ``NAME`` (runs of two versions of the code side by side, which may differ in more
than their configs), and ``table1.md`` lists what each named folder set apart from the paper preset:

    python recipes/report.py tier1=results/100000 release=results/100000-release --budget 100000

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
import csv
import functools
import json
import math
import re
import textwrap
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from screen import bootstrap_interval  # noqa: E402

#: The paper's Table 1 (1.5M steps, mean of 5 seeds): return, manual resets, forward share, success rate.
PAPER_TABLE1 = {
    ("ball_in_cup_catch", "lnt"): (10.38, 276, 0.857, 0.993),
    ("ball_in_cup_catch", "ours"): (19.51, 331, 0.797, 0.968),
    ("ball_in_cup_catch", "lnt_sparse"): (5.48, 358, 0.890, 0.975),
    ("peg_insertion_insert", "lnt"): (30.50, 251, 0.717, 0.985),
    ("peg_insertion_insert", "ours"): (29.20, 343, 0.663, 0.966),
    ("peg_insertion_insert", "lnt_sparse"): (1.60, 7175, 0.026, 0.744),
    ("cliff_cheetah", "lnt"): (4.77, 835, 0.150, 0.857),
    ("cliff_cheetah", "ours"): (1.96, 371, 0.314, 0.948),
    ("cliff_cheetah", "lnt_sparse"): (2.96, 765, 0.154, 0.803),
    ("ball_in_cup_throw", "lnt"): (33.28, 359, 0.754, 0.991),
    ("ball_in_cup_throw", "ours"): (17.75, 1231, 0.479, 0.949),
    ("ball_in_cup_throw", "lnt_sparse"): (31.70, 1527, 0.525, 0.878),
    ("peg_insertion_remove", "lnt"): (44.57, 1714, 0.489, 0.931),
    ("peg_insertion_remove", "ours"): (30.27, 2525, 0.326, 0.712),
    ("peg_insertion_remove", "lnt_sparse"): (0.46, 7407, 0.006, 0.353),
    ("cliff_walker", "lnt"): (6.65, 1195, 0.057, 0.957),
    ("cliff_walker", "ours"): (6.29, 1305, 0.042, 0.687),
    ("cliff_walker", "lnt_sparse"): (0.00, 1415, 0.001, 0.949),
}
TASK_TITLES = {
    "ball_in_cup_catch": "ball-in-cup (catch)", "peg_insertion_insert": "peg-insertion (insert)",
    "cliff_cheetah": "cliff-cheetah", "ball_in_cup_throw": "ball-in-cup (throw)",
    "peg_insertion_remove": "peg-insertion (remove)", "cliff_walker": "cliff-walker",
}
ALGO_TITLES = {"ours": "ours", "lnt": "LNT", "lnt_sparse": "LNT-sparse", "lnt_release": "LNT (release's ensemble)",
               "lnt_sparse_release": "LNT-sparse (release's ensemble)"}
METRICS = ("average_return", "manual_resets", "forward_share", "reset_success_rate")
COLORS = {"ours": "tab:red", "lnt": "tab:blue", "lnt_sparse": "tab:green", "lnt_release": "tab:cyan",
          "lnt_sparse_release": "tab:olive"}
#: Settings that say how a run was executed, recorded or how long it ran, not what it learns (p_thresh is
#: a grouping of its own, Fig. 4). Runs of one task and algorithm that differ in anything else are
#: different settings: reported side by side, never averaged together. Older runs' configs also hold the
#: keys of run batching, retired (``seeds``, ``arms``, ``vary``, ``vary_values``: null in a single run;
#: ``speed.batched_acting``), which are no setting either.
NOT_A_SETTING = ("seed", "seeds", "arms", "vary", "vary_values", "device", "threads", "sweep_dir", "run_dir", "resume",
                 "total_steps", "task.total_steps", "eval_every", "log_every", "checkpoint_every",
                 "keep_checkpoints", "keep_states_every", "progress_bar", "logger", "speed", "task.p_thresh")
PAPER_SETTING = "paper's setting"


class RunFolder:
    """One run folder: its summary, config and logged tables; with ``budget``, everything as it stood
    at that many steps (the counters of the last ``progress.csv`` row at or before it, the
    evaluations up to it), so that runs that went on longer are compared at the same budget."""

    def __init__(self, folder: Path, budget: int | None = None):
        from omegaconf import OmegaConf

        self.folder = folder
        self.budget = budget
        self.config = OmegaConf.load(folder / "config.yaml") if (folder / "config.yaml").exists() else None
        if (folder / "summary.json").exists():
            self.summary = json.loads((folder / "summary.json").read_text())
        else:  # a run still going (or killed): read as it stands from its config and logs
            cfg = self.config
            self.summary = {"task": cfg.task.name, "algo": cfg.algo.name, "seed": int(cfg.seed),
                            "p_thresh": float(cfg.task.p_thresh), "finished": False}
            self.summary.update(self._at_budget(budget if budget is not None else 2**62))
        for key in ("task", "algo", "seed", *METRICS):
            if key not in self.summary:
                raise ValueError(f"{folder / 'summary.json'} has no {key!r}: not written by train.py?")
        self.task, self.algo = self.summary["task"], self.summary["algo"]
        self.p_thresh = self.summary.get("p_thresh")
        self.setting = ""  # what sets this run apart from others of its task and algo (assign_settings)
        self.source: str | None = None  # the name given to the folder it was found under (find_runs)
        if budget is not None:
            self.summary = {**self.summary, **self._at_budget(budget)}
        elif not self.summary.get("finished", True):
            # a run resumed after its summary was written: read it as it stands now
            frames = self.table("progress.csv").get("frames", [])
            if len(frames) and frames[-1] > self.summary.get("steps", 0):
                self.summary = {**self.summary, **self._at_budget(2**62)}
        self.summary.update(self._resets_saved())

    def table(self, name: str, text: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
        """The columns of ``name`` as float arrays (the columns named in ``text`` as strings, such as
        ``resets.csv``'s ``outcome``), with a budget only the rows at or before it."""
        path = self.folder / name
        if not path.exists():
            return {}
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
        if not rows:
            return {}
        data = {key: np.array([row[key] if key in text else _float(row[key]) for row in rows])
                for key in rows[0] if key != "observation"}
        if self.budget is not None and "frames" in data:
            keep = data["frames"] <= self.budget
            data = {key: values[keep] for key, values in data.items()}
        return data

    def _at_budget(self, budget: int) -> dict:
        progress = self.table("progress.csv")
        if not len(progress.get("frames", [])):
            raise ValueError(f"{self.folder}: no progress.csv row at or before step {budget}.")
        last = {key: values[-1] for key, values in progress.items()}
        out = {"steps": int(last["frames"])}
        if "manual_resets" in last:
            out["manual_resets"] = int(last["manual_resets"])
        if "forward_steps" in last and "reset_steps" in last:
            out["forward_share"] = float(last["forward_steps"] / max(last["forward_steps"] + last["reset_steps"], 1))
        if "successful_resets" in last and "manual_resets" in last:
            ended = last["successful_resets"] + last["manual_resets"]
            out["reset_success_rate"] = float(last["successful_resets"] / ended) if ended else math.nan
        returns = self.table("eval.csv").get("forward_return", np.zeros(0))
        out["average_return"] = float(np.mean(returns)) if len(returns) else math.nan
        return out

    def _resets_saved(self) -> dict:
        """Resets an episodic agent would have needed (one per forward episode) and the manual resets
        per 1000 steps over the last quarter of the (budgeted) run."""
        progress = self.table("progress.csv")
        out = {"episodic_resets": math.nan, "baseline_hard_resets": math.nan, "late_manual_rate": math.nan}
        frames = progress.get("frames", np.zeros(0))
        if not len(frames):
            return out
        if "forward_episodes" in progress:
            out["episodic_resets"] = float(progress["forward_episodes"][-1])
            if self.budget is None and self.summary.get("episodic_resets") is not None:
                out["episodic_resets"] = float(self.summary["episodic_resets"])  # at the same step as manual_resets
        from omegaconf import OmegaConf

        horizon = None if self.config is None else OmegaConf.select(self.config, "task.forward_horizon", default=None)
        if "forward_steps" in progress and "triggered_resets" in progress and horizon:
            # the release's baseline: one hard reset per H_f forward step calls, triggered ones included
            calls = progress["forward_steps"][-1] + progress["triggered_resets"][-1]
            out["baseline_hard_resets"] = float(calls // horizon)
        if self.budget is None and self.summary.get("baseline_hard_resets") is not None:
            out["baseline_hard_resets"] = float(self.summary["baseline_hard_resets"])  # as episodic_resets above
        if "manual_resets" in progress and len(frames) >= 2:
            end = frames[-1]
            start = int(np.searchsorted(frames, end - end / 4, side="right")) - 1
            if start >= 0 and end > frames[start]:
                manual = progress["manual_resets"]
                out["late_manual_rate"] = float(1000 * (manual[-1] - manual[start]) / (end - frames[start]))
        return out


def _flatten(node, prefix: str = "") -> dict:
    """A config as ``{"algo.initial_logit_bias": -4, ...}`` (lists as tuples), without ``NOT_A_SETTING``."""
    out = {}
    for key, value in node.items():
        name = f"{prefix}{key}"
        if any(name == k or name.startswith(f"{k}.") for k in NOT_A_SETTING):
            continue
        if isinstance(value, dict):
            out.update(_flatten(value, f"{name}."))
        else:
            out[name] = tuple(value) if isinstance(value, list) else value
    return out


@functools.lru_cache(maxsize=None)
def recipe_defaults(task: str, algo: str) -> dict:
    """The settings ``train.py preset=paper task=<task> algo=<algo>`` runs with (the paper's preset), flattened; empty
    for a task or algorithm this checkout does not know. Keys that older runs' configs lack (a setting
    added since) take these values."""
    conf = Path(__file__).resolve().parent / "conf"
    if not (conf / "task" / f"{task}.yaml").exists() or not (conf / "algo" / f"{algo}.yaml").exists():
        return {}
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["preset=paper", f"task={task}", f"algo={algo}"])
    return _flatten(OmegaConf.to_container(cfg, resolve=True))


def _value_text(value) -> str:
    if value is None:
        return "null"
    if isinstance(value, tuple):
        return "[" + ",".join(map(_value_text, value)) + "]"
    return str(value)


def assign_settings(runs: list[RunFolder]) -> None:
    """Give each run the settings that set it apart from the other runs of its task and algorithm
    (``run.setting``: ``""`` where all agree, ``"paper's setting"`` for the recipe's defaults, else
    ``key=value`` overrides such as ``algo.initial_logit_bias=-4``; runs under a named folder: its name, then
    what differs between them), so that the report keeps them apart."""
    for (task, algo), members in _by(runs, "task", "algo").items():
        defaults = recipe_defaults(task, algo)
        settings = [run_settings(run, defaults) for run in members]
        # a named folder is its own setting; within it, runs are told apart by what differs between them
        for source in dict.fromkeys(run.source for run in members):
            group = [(run, own) for run, own in zip(members, settings) if run.source == source]
            labels = _setting_labels([own for _, own in group], defaults, among=source is not None)
            for (run, _), label in zip(group, labels):
                if source is not None:  # "NAME", or "NAME, key=value" for what this run changed inside it
                    label = ", ".join(filter(None, [source, "" if label == PAPER_SETTING else label]))
                run.setting = label


def run_settings(run: RunFolder, defaults: dict) -> dict:
    """What ``run`` ran with, flattened: its ``config.yaml``, a key it lacks read as what its absence meant
    when it ran (``absent_keys.ABSENT_KEYS``: the behaviour before the key existed), any other key as the
    recipe's default."""
    from absent_keys import ABSENT_KEYS
    from omegaconf import OmegaConf

    if run.config is None:
        return dict(defaults)
    absent = {k: v for k, v in ABSENT_KEYS.items() if k in defaults}  # keys of this task and algorithm only
    return {**defaults, **absent, **_flatten(OmegaConf.to_container(run.config, resolve=False))}


def _setting_labels(settings: list[dict], defaults: dict, among: bool = False) -> list[str]:
    """For runs of one task and algorithm: ``""`` where all agree, else each run's ``key=value`` pairs that
    differ from ``defaults`` (``PAPER_SETTING`` where none does; where the defaults are unknown, the pairs
    that differ between the runs). ``among``: only the pairs that also differ between the runs (inside a
    named folder, whose name says the rest)."""
    keys = sorted({k for s in settings for k in s})
    missing = object()
    differ = [k for k in keys if len({repr(s.get(k, missing)) for s in settings}) > 1]
    labels = []
    for own in settings:
        # where the defaults are known, everything this run changed from them, also what all runs changed
        # alike (runs of an older preset beside one option are not the paper's setting)
        candidates = differ if among or not defaults else sorted(set(own) | set(defaults))
        changed = [k for k in candidates if not defaults or repr(own.get(k, missing)) != repr(defaults.get(k, missing))]
        if not differ:
            labels.append("")
        elif not changed:
            labels.append(PAPER_SETTING)
        else:
            labels.append(", ".join(
                f"{k}={'(unset)' if own.get(k, missing) is missing else _value_text(own[k])}" for k in changed))
    return labels


def named_settings(runs: list[RunFolder]) -> list[str]:
    """For each named folder, per algorithm, what its runs set apart from the recipe's paper preset."""
    lines = []
    for (source, task, algo), members in sorted(_by([r for r in runs if r.source], "source", "task", "algo").items()):
        defaults = recipe_defaults(task, algo)
        changed = sorted({f"{k}={_value_text(own[k])}" for own in (run_settings(r, defaults) for r in members)
                          for k in own if defaults and k in defaults and repr(own[k]) != repr(defaults[k])
                          and not any(k == n or k.startswith(f"{n}.") for n in NOT_A_SETTING)})
        lines.append(f"- {source}, {TASK_TITLES.get(task, task)}, {ALGO_TITLES.get(algo, algo)}: "
                     + (", ".join(changed) if changed else "the paper preset's settings"))
    return lines


def _is_paper_setting(setting: str) -> bool:
    """The only setting of its group, or the recipe's defaults (the paper's)."""
    return setting in ("", PAPER_SETTING)


def _title(algo: str, setting: str) -> str:
    return ALGO_TITLES.get(algo, algo) + (f" ({setting})" if setting else "")


def _file_suffix(setting: str) -> str:
    """``""`` for the only or the paper's setting, else the setting as a file-name part."""
    if _is_paper_setting(setting):
        return ""
    return "_" + re.sub(r"[^A-Za-z0-9_.-]+", "_", setting.replace("=", ""))


def _float(value: str) -> float:
    try:
        return float(value)
    except ValueError:
        return {"True": 1.0, "False": 0.0}.get(value, math.nan)


def find_runs(paths: list[Path], budget: int | None = None, names: dict[Path, str] | None = None) -> list[RunFolder]:
    """Run folders: those with a ``summary.json``, and runs still going (``config.yaml`` and ``progress.csv``).
    ``names``: a name for some of ``paths``; the runs found under a named path are that name's setting."""
    folders, source = set(), {}
    for path in paths:
        found = set()
        if path.is_file():
            found.add(path.parent)
        else:
            found |= {p.parent for p in path.rglob("summary.json")}
            found |= {p.parent for p in path.rglob("progress.csv") if (p.parent / "config.yaml").exists()}
        if names and path in names:
            source.update(dict.fromkeys(found, names[path]))
        folders |= found
    folders = sorted(folders)
    if not folders:
        raise SystemExit(f"no summary.json under {', '.join(map(str, paths))}: nothing to report.")
    runs = []
    for folder in folders:
        try:
            runs.append(RunFolder(folder, budget))
            runs[-1].source = source.get(folder)
        except ValueError as err:
            if budget is None or "no progress.csv row" not in str(err):
                raise
            print(f"left out: {err}")  # a run that had not logged anything by the budget
    if not runs:
        raise SystemExit(f"no run had logged anything by step {budget}: nothing to report.")
    assign_settings(runs)
    return runs


def _mean_std(values: list[float]) -> tuple[float, float, float, float]:
    """Mean, population standard deviation and, over three or more values, the mean's bootstrap 95% interval
    (``screen.bootstrap_interval``; NaN below three)."""
    values = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    if not values:
        return math.nan, math.nan, math.nan, math.nan
    _, low, high = bootstrap_interval(values)
    return float(np.mean(values)), float(np.std(values)) if len(values) > 1 else 0.0, low, high


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


def _reached(run: RunFolder) -> bool:
    return run.budget is None or run.summary.get("steps", 0) >= run.budget


def _complete(groups: dict) -> tuple[dict, list[RunFolder]]:
    """With a budget, each group's runs that reached it; runs short of it are left out of the means
    (listed apart) unless no run of their group reached it (the row is then marked in progress)."""
    kept, short = {}, []
    for key, members in groups.items():
        done = [r for r in members if _reached(r)]
        kept[key] = done or members
        short += [r for r in members if not _reached(r)] if done else []
    return kept, short


def _row_order(task: str, algo: str, setting: str, p_thresh) -> tuple:
    order = list(TASK_TITLES)
    return (order.index(task) if task in order else 99, algo, not _is_paper_setting(setting), setting,
            p_thresh or 0)


def table1(runs: list[RunFolder]) -> str:
    """Markdown table: one row per (task, algo, setting, p_thresh) group, mean ± std over its seeds, paper beside
    (the paper's numbers only on its own setting's rows)."""
    groups, short = _complete(_by(runs, "task", "algo", "setting", "p_thresh"))
    kinds = ("return", "count", "share", "share")
    lines = [
        "| task | algo | p_thresh | seeds | steps | avg return | manual resets | forward share | success rate |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for (task, algo, setting, p_thresh), members in sorted(groups.items(), key=lambda kv: _row_order(*kv[0])):
        paper = PAPER_TABLE1.get((task, algo)) if _is_paper_setting(setting) else None
        cells = []
        for metric, kind, index in zip(METRICS, kinds, range(4)):
            cell = _cell(*_mean_std([r.summary[metric] for r in members]), kind=kind)
            if paper is not None:
                cell += f" (paper {_paper(paper[index], kind)})"
            cells.append(cell)
        steps = "/".join(map(str, sorted({r.summary.get("steps") for r in members})))
        if not all(_reached(r) for r in members):
            steps += " (in progress)"
        lines.append(
            f"| {TASK_TITLES.get(task, task)} | {_title(algo, setting)} | {p_thresh} | {len(members)} | "
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
            f"{_title(r.algo, r.setting)} seed {r.summary['seed']} at {r.summary.get('steps')} steps"
            for r in sorted(short, key=lambda r: (r.algo, r.setting, r.summary["seed"]))) + ".")
    lines += [
        "",
        "| task | algo | p_thresh | seeds | manual resets | episodic resets | saved | release's baseline "
        "| saved | manual resets per 1k steps, last quarter |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for (task, algo, setting, p_thresh), members in sorted(groups.items(), key=lambda kv: _row_order(*kv[0])):
        manual = _mean_std([r.summary["manual_resets"] for r in members])
        episodic = _mean_std([r.summary["episodic_resets"] for r in members])
        saved = _mean_std([r.summary["episodic_resets"] - r.summary["manual_resets"] for r in members])
        late = _mean_std([r.summary["late_manual_rate"] for r in members])
        by_steps = _mean_std([r.summary["baseline_hard_resets"] for r in members])
        saved_by_steps = _mean_std([r.summary["baseline_hard_resets"] - r.summary["manual_resets"] for r in members])
        lines.append(
            f"| {TASK_TITLES.get(task, task)} | {_title(algo, setting)} | {p_thresh} | {len(members)} | "
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


def _curves(members: list[RunFolder], table: str, column: str):
    """Per-run (steps, values) curves of ``column`` from ``table``."""
    out = []
    for run in members:
        data = run.table(table)
        if column in data and "frames" in data:
            out.append((data["frames"], data[column]))
    return out


def _plot_band(ax, curves, color, label, linestyle="-", band=True, **line):
    """The mean over runs of ``curves`` (with ``band``, their range shaded); returns the mean's line."""
    if not curves:
        return None
    grid = np.unique(np.concatenate([x for x, _ in curves]))
    stacked = np.array([np.interp(grid, x, y, left=np.nan, right=np.nan) for x, y in curves])
    with np.errstate(all="ignore"):
        mean = np.nanmean(stacked, axis=0)
    if len(grid) < 3:
        line = {**line, "marker": "o"}  # a lone point shows
    (mean_line,) = ax.plot(grid, mean, color=color, ls=linestyle, label=f"{label} (n={len(curves)})", **line)
    if band and len(curves) > 1:
        ax.fill_between(grid, np.nanmin(stacked, axis=0), np.nanmax(stacked, axis=0), color=mean_line.get_color(),
                        alpha=0.2)
    return mean_line


def _by(runs: list[RunFolder], *attributes: str) -> dict[tuple, list[RunFolder]]:
    groups = defaultdict(list)
    for run in runs:
        groups[tuple(getattr(run, a) for a in attributes)].append(run)
    return groups


def _steps_label(value: float, _position=None) -> str:
    """Step counts on an axis as 0, 500, 2k, 12.5k, 1.5M."""
    if abs(value) >= 1e6:
        return f"{value / 1e6:g}M"
    return f"{value / 1e3:g}k" if abs(value) >= 1e3 else f"{value:g}"


def _save(fig, path: Path, written: list[Path]) -> None:
    from matplotlib.ticker import FuncFormatter

    for ax in fig.axes:
        if ax.get_xlabel().startswith("steps"):
            ax.xaxis.set_major_formatter(FuncFormatter(_steps_label))
    if fig.get_layout_engine() is None:  # figures laid out with constrained layout keep it
        fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)


NOTE_PLACES = {"centre": (0.5, 0.62, "center", "center"), "upper left": (0.02, 0.97, "left", "top"),
               "lower right": (0.98, 0.03, "right", "bottom")}


def _panel_note(ax, text: str, where: str = "centre") -> None:
    """A boxed note on a panel: what it shows where its data cannot (nothing yet, a check not drawn)."""
    x, y, ha, va = NOTE_PLACES[where]
    ax.text(x, y, text, ha=ha, va=va, transform=ax.transAxes, fontsize=8.5, zorder=5,
            bbox=dict(boxstyle="round", facecolor="white", edgecolor="0.6", alpha=0.9))


def figure3_groups(task_runs: list[RunFolder]) -> dict[str, tuple[list[RunFolder], str]]:
    """Fig. 3's runs per algorithm (and setting, where runs differ in one) and their legend label: the runs
    the table's means take (with a budget, those that reached it, so that no band jumps where a shorter run
    ends). Keys: the algorithm, with `` (<setting>)`` where its runs differ in settings."""
    kept, _ = _complete(_by(task_runs, "algo", "setting"))
    groups = {}
    for (algo, setting), members in sorted(kept.items(), key=lambda kv: _row_order("", *kv[0], None)):
        label = _title(algo, setting)
        key = algo + (f" ({setting})" if setting else "")
        groups[key] = (members, label if all(map(_reached, members)) else f"{label}, in progress")
    return groups


def _line_style(setting: str, others: list[str]) -> str:
    """Solid for the only or the paper's setting; dashed, dotted, dash-dotted for the others in turn."""
    if _is_paper_setting(setting):
        return "-"
    variants = sorted(s for s in others if not _is_paper_setting(s))
    return ("--", ":", "-.")[variants.index(setting) % 3]


def _episodic_style(style: str, settings_differ: bool, plain: str = "--") -> dict:
    """Fig. 3's companion line (the resets an episodic agent would have needed; the falls in reset steps) beside
    a group drawn in ``style``: thin and ``plain`` (dashed); where settings already take the line styles, thin in
    its group's style with hollow markers, so that it is told apart from every other line of the panel."""
    if not settings_differ:
        return {"linestyle": plain, "lw": 1.2}
    return {"linestyle": style, "lw": 1.2, "marker": "o", "mfc": "none", "ms": 3.5, "markevery": 0.1}


def _config_value(run: RunFolder, key: str):
    from omegaconf import OmegaConf

    return None if run.config is None else OmegaConf.select(run.config, key, default=None)


def _return_note(members: list[RunFolder]) -> str | None:
    """Why a group's forward-return curve is missing or flat: no evaluation yet, or every return 0."""
    returns = [run.table("eval.csv").get("forward_return", np.zeros(0)) for run in members]
    returns = np.concatenate(returns) if returns else np.zeros(0)
    if not len(returns):
        every = sorted({int(v) for v in (_config_value(run, "eval_every") for run in members) if v is not None})
        return "no evaluation yet" + (f" (every {' or '.join(f'{v:,}' for v in every)} steps)" if every else "")
    if np.all(returns == 0):
        return "forward return 0 at every evaluation so far"
    return None


def _fit_episodic(ax, manual_lines: list, episodic_lines: list, room: float = 2.0) -> None:
    """Keep the manual resets readable: where an episodic count exceeds ``room`` times the most manual resets
    (LNT's trigger cuts many forward episodes short), the panel stops above the other lines and the legend
    gives the count that leaves it."""
    top = max((np.nanmax(line.get_ydata()) for line in manual_lines if len(line.get_ydata())), default=0.0)
    if not top > 0:
        return
    peaks = [(line, np.nanmax(line.get_ydata())) for line in episodic_lines if len(line.get_ydata())]
    if all(peak <= room * top for _, peak in peaks):
        return
    limit = 1.08 * max([top] + [peak for _, peak in peaks if peak <= room * top])
    ax.set_ylim(-0.03 * limit, limit)
    for line, peak in peaks:
        if peak > room * top:
            x, y = line.get_xdata()[-1], line.get_ydata()[-1]
            line.set_label(f"{line.get_label()}\noff the scale: {y:,.0f} at {_steps_label(x)} steps")


def fig3_figure(task: str, task_runs: list[RunFolder]):
    """Fig. 3 of one task: the evaluation forward return and the cumulative manual resets against steps, one
    band per algorithm (and setting), each beside the resets an episodic agent would have needed (one per
    forward episode, ``forward_episodes``), with a note where a return curve is missing or flat. On a task with
    irrecoverable states (runs that log ``irrecoverable_forward``: the cliff tasks), a third panel: the
    cumulative entries into the ditch in forward steps (the group's line, with the band) and in reset steps (its
    companion line: thin and dotted)."""
    from torchrl_reset_envs import TASKS

    spec = TASKS.get(task)
    falls = bool(getattr(spec, "has_irrecoverable", False)) and any(
        "irrecoverable_forward" in run.table("progress.csv") for run in task_runs)
    lost = "the ditch" if hasattr(getattr(spec, "env_class", None), "in_ditch") else "an irrecoverable state"
    fig, axes = plt.subplots(1, 3 if falls else 2, figsize=(15 if falls else 10, 3.8))
    ax_ret, ax_man = axes[:2]
    settings = sorted({r.setting for r in task_runs})
    settings_differ = len({_line_style(s, settings) for s in settings}) > 1
    groups = figure3_groups(task_runs)
    notes, manual_lines, episodic_lines = {}, [], []
    for members, label in groups.values():
        color, style = COLORS.get(members[0].algo), _line_style(members[0].setting, settings)
        _plot_band(ax_ret, _curves(members, "eval.csv", "forward_return"), color, label, style)
        manual = _plot_band(ax_man, _curves(members, "progress.csv", "manual_resets"), color, label, style)
        episodic = _plot_band(ax_man, _curves(members, "progress.csv", "forward_episodes"),
                              manual.get_color() if manual is not None else color, f"{label}: episodic", band=False,
                              **_episodic_style(style, settings_differ))
        manual_lines += [manual] if manual is not None else []
        episodic_lines += [episodic] if episodic is not None else []
        if falls:
            into = _plot_band(axes[2], _curves(members, "progress.csv", "irrecoverable_forward"), color,
                              f"{label}: forward", style)
            _plot_band(axes[2], _curves(members, "progress.csv", "irrecoverable_reset"),
                       into.get_color() if into is not None else color, f"{label}: reset", band=False,
                       **_episodic_style(style, settings_differ, plain=":"))
        note = _return_note(members)
        if note is not None:
            notes[label] = note
    if notes:
        whole = len(notes) == len(groups) and len(set(notes.values())) == 1
        text = next(iter(notes.values())) if whole else "\n".join(f"{label}: {note}" for label, note in notes.items())
        _panel_note(ax_ret, text, "centre" if len(notes) == len(groups) else "lower right")
    _fit_episodic(ax_man, manual_lines, episodic_lines)
    ax_ret.set(title=f"{TASK_TITLES.get(task, task)}: forward return", xlabel="steps (forward + reset)",
               ylabel="discounted return (evaluation)")
    ax_man.set(title="cumulative manual resets\nand an episodic agent's (one per forward episode)",
               xlabel="steps (forward + reset)", ylabel="resets")
    if falls:
        axes[2].set(title=f"cumulative entries into {lost}\n(in forward steps; in reset steps: thin)",
                    xlabel="steps (forward + reset)", ylabel="entries")
        axes[2].set_ylim(bottom=0)
        if not any(np.nanmax(line.get_ydata(), initial=0) > 0 for line in axes[2].get_lines()):
            _panel_note(axes[2], f"no entry into {lost} so far")
    for ax in axes:
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    return fig


def figure3(runs: list[RunFolder], out: Path) -> list[Path]:
    written = []
    for (task,), task_runs in _by(runs, "task").items():
        _save(fig3_figure(task, task_runs), out / f"fig3_{task}.png", written)
    return written


def figure4(runs: list[RunFolder], out: Path) -> list[Path]:
    written = []
    for (task, algo, setting), members in _by(runs, "task", "algo", "setting").items():
        thresholds = sorted({r.p_thresh for r in members if r.p_thresh is not None})
        if len(thresholds) < 2:
            continue
        fig, axes = plt.subplots(1, 4, figsize=(14, 3.4))
        for ax, metric in zip(axes, METRICS):
            stats = [_mean_std([r.summary[metric] for r in members if r.p_thresh == p]) for p in thresholds]
            ax.errorbar(thresholds, [m for m, *_ in stats], yerr=[s for _, s, *_ in stats], marker="o", capsize=3,
                        color=COLORS.get(algo))
            ax.set(xlabel="p_thresh", title=metric.replace("_", " "))
            ax.grid(alpha=0.3)
        fig.suptitle(f"{TASK_TITLES.get(task, task)}, {_title(algo, setting)}: p_thresh sweep")
        _save(fig, out / f"fig4_{task}_{algo}{_file_suffix(setting)}.png", written)
    return written


def _run_labels(members: list[RunFolder]) -> list[str]:
    """``seed k`` for each run, with its p_thresh where the runs differ in it."""
    sweep = len({run.p_thresh for run in members}) > 1
    return [f"seed {run.summary['seed']}" + (f", p_thresh {run.p_thresh}" if sweep else "") for run in members]


def fig5_figure(task: str, algo: str, setting: str, members: list[RunFolder]):
    """Fig. 5 of one task and algorithm: the curriculum entry of the state just before each triggered reset
    against steps, per run; a run without any triggered reset is named on the figure."""
    fig, ax = plt.subplots(figsize=(6, 3.8))
    quiet = []
    for run, label, color in zip(members, _run_labels(members), _run_colors(len(members))):
        points = run.table("triggers.csv")
        if len(points.get("frames", ())):
            # a trigger in a state already irrecoverable (over the cliff) came too late: drawn as a cross
            lost = points.get("irrecoverable", np.zeros(len(points["frames"]))) == 1
            ax.scatter(points["frames"][~lost], points["value"][~lost], s=6, alpha=0.5, color=color, label=label)
            if lost.any():
                ax.scatter(points["frames"][lost], points["value"][lost], s=14, marker="x", color=color,
                           label=f"{label}: already irrecoverable ({int(lost.sum())})")
        else:  # train.py writes triggers.csv at the first triggered reset: no file, no trigger
            quiet.append((run, label))
    edge = cliff_edge(members[0])
    if edge is not None:
        ax.axhline(edge, color="k", ls="--", lw=1, label=f"cliff edge (x = {edge:g})")
    if quiet:
        if len(quiet) == len(members):
            steps = max(run.summary.get("steps", 0) for run in members)
            text = ("no triggered reset in this run" if len(members) == 1 else
                    f"no triggered reset in these {len(members)} runs") + (f" ({steps:,} steps)" if steps else "")
        else:
            text = "no triggered reset in " + ", ".join(label for _, label in quiet)
        _panel_note(ax, text, "centre" if len(quiet) == len(members) else "lower right")
    ax.set(title=f"{TASK_TITLES.get(task, task)}, {_title(algo, setting)}: state before each trigger",
           xlabel="steps (forward + reset)", ylabel=_curriculum_label(members[0]))
    ax.set_xlim(0, max(run.summary.get("steps", 0) for run in members) or None)  # the whole run, quiet stretches too
    ax.grid(alpha=0.3)
    if len(quiet) < len(members) or edge is not None:
        ax.legend(fontsize=8, markerscale=2)
    return fig


def cliff_edge(run: RunFolder) -> float | None:
    """The cliff's edge on Fig. 5's axis: the task's ``edge`` where Fig. 5 plots the x position (observation
    entry 0, the cliff tasks' curriculum), else None."""
    from omegaconf import OmegaConf
    from stretches import run_task

    cfg, spec = run_task(run.folder)
    edge = getattr(getattr(spec, "env_class", None), "edge", None)
    return None if edge is None or OmegaConf.select(cfg, "task.curriculum.index") != 0 else float(edge)


def figure5(runs: list[RunFolder], out: Path) -> list[Path]:
    written = []
    for (task, algo, setting), members in _by(runs, "task", "algo", "setting").items():
        _save(fig5_figure(task, algo, setting, members), out / f"fig5_{task}_{algo}{_file_suffix(setting)}.png",
              written)
    return written


#: Each task's reset-success check (``reset_success``, docs/environments.md) as the diagnostics' distance
#: panel can show it: the check in words, and its bound on that panel's distance (the observation's distance
#: to the start state) where the check is one, else ``None``: no line is drawn for a check on other
#: quantities (peg-insertion (insert) bounds the peg's position, not the arm's joint angles and velocities).
RESET_SUCCESS = {
    "cliff_cheetah": ("|x| < 0.1 and |pitch| < 0.1", None),
    "cliff_walker": ("|x| < 0.5, |h - 1.3| < 0.3 and |pitch| < 1", None),
    "peg_insertion_insert": ("the peg within 0.2 m of its start (its two ends' positions)", None),
    "peg_insertion_remove": ("the peg in the hole", None),
    "ball_in_cup_catch": ("the ball hanging still below a centred cup", None),
    "ball_in_cup_throw": ("the ball resting in the cup", None),
    "ur3_peg": ("every joint within 0.05 rad of home", None),
    "ur3_reacher": ("every joint within 0.05 rad of home and the stick not spilled", None),
}
#: How the distance panel marks each reset episode's outcome (``resets.csv``).
OUTCOME_MARKERS = {"success": "o", "manual": "x", "terminated": "s"}
#: The reset model's probes (``diagnostics.csv``) in the diagnostics figure: column, legend label, line style.
PROBE_SERIES = (("example_p", "examples", "-"), ("reset_replay_p", "reset replay", "--"),
                ("forward_p", "forward replay", "-."), ("forward_p_min_member", "forward replay, lowest member", ":"))
DIAGNOSTICS_LEGEND_SIZE = 8


def _run_colors(n: int) -> list:
    """One colour per run: the 10-colour cycle, or evenly spaced colours where there are more runs."""
    if n <= 10:
        return [f"C{i}" for i in range(n)]
    return [tuple(c) for c in plt.get_cmap("turbo")(np.linspace(0.05, 0.95, n))]


def _trigger_thresholds(algo: str, members: list[RunFolder]) -> list[tuple[str, float]]:
    """The trigger's threshold lines: ours' p_thresh (the threshold its trigger used), LNT's Q_thresh
    (``algo.threshold`` of the run's config)."""
    if algo == "ours":
        values = {float(run.p_thresh) for run in members if run.p_thresh is not None}
        return [(f"p_thresh = {v:g}", v) for v in sorted(values)]
    values = {float(v) for v in (_config_value(run, "algo.threshold") for run in members) if v is not None}
    return [(f"Q_thresh = {v:g}", v) for v in sorted(values)]


def _stretch(tables: list[dict]) -> int:
    """The diagnostics' success-rate stretch in steps: a twentieth of the longest run, in whole log rows."""
    frames = [t["frames"] for t in tables if len(t.get("frames", ())) > 1]
    if not frames:
        return 0
    row = max(1, int(np.median(np.concatenate([np.diff(f) for f in frames]))))
    longest = max(float(f[-1]) for f in frames)
    return row * max(1, round(longest / 20 / row))


def success_rate_per_stretch(frames, successful, manual, stretch: float) -> np.ndarray:
    """At each log row, the share of the reset episodes that ended within ``stretch`` steps centred on it
    that reached the start (``successful / (successful + manual)``, from the cumulative counts at the rows
    around it); NaN where none ended."""
    frames = np.asarray(frames, dtype=float)

    def at(cumulative, steps):  # the count at the last row at or before ``steps``; 0 before the first
        index = np.searchsorted(frames, steps, side="right") - 1
        return np.where(index >= 0, np.asarray(cumulative, dtype=float)[np.maximum(index, 0)], 0.0)

    lo, hi = frames - stretch / 2, frames + stretch / 2
    success = at(successful, hi) - at(successful, lo)
    ended = success + at(manual, hi) - at(manual, lo)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ended > 0, success / ended, np.nan)


def diagnostics_figure(task: str, algo: str, setting: str, members: list[RunFolder]):
    """What explains a run (``diagnostics.csv``, ``resets.csv``, ``progress.csv``) for one task and algo, or
    ``None`` where no run logged diagnostics: the trigger's score on executed forward steps against its
    threshold, the reset model on examples, reset replay and forward replay, the reset success rate per
    stretch of the run, and how far each reset episode ended from the start, marked by its outcome. One
    colour per run throughout; the series within a panel differ in line style or marker. Ours' scores are
    the ensemble-mean success probability p (threshold p_thresh); LNT's the reset Q-ensemble's minimum Q
    (threshold Q_thresh)."""
    from matplotlib.lines import Line2D

    tables = [(run, run.table("diagnostics.csv")) for run in members]
    tables = [(run, t) for run, t in tables if "frames" in t]
    if not tables:
        return None
    runs = [run for run, _ in tables]
    ours = algo == "ours"
    score = "p: ensemble-mean success probability" if ours else "Q: reset Q-ensemble's minimum"
    # LNT's trigger takes the members' minimum, so the lowest member is the forward-replay line itself
    probes = [probe for probe in PROBE_SERIES if ours or probe[0] != "forward_p_min_member"]
    progress = [run.table("progress.csv") for run in runs]
    stretch = _stretch(progress)
    saturation = any("reset_saturation" in prog for prog in progress)  # runs that logged it (every run since it exists)
    fig, axes = plt.subplots(1, 5 if saturation else 4, figsize=(22.5 if saturation else 18, 4.8), layout="constrained")
    colors, labels = _run_colors(len(runs)), _run_labels(runs)
    outcomes_seen = []
    for (run, t), color, label, prog in zip(tables, colors, labels, progress):
        for column, name, style in (("trigger_score_mean", "mean", "-"), ("trigger_score_min", "lowest", ":")):
            if column in t:
                axes[0].plot(t["frames"], t[column], color=color, ls=style, label=f"{label}: {name}")
        for column, name, style in probes:
            if column in t:
                axes[1].plot(t["frames"], t[column], color=color, ls=style, label=f"{label}: {name}")
        if "successful_resets" in prog and "manual_resets" in prog and len(prog["frames"]) > 1:
            rate = success_rate_per_stretch(prog["frames"], prog["successful_resets"], prog["manual_resets"], stretch)
            axes[2].plot(prog["frames"], rate, color=color, label=label)
        if saturation:
            for column, style, actor in (("reset_saturation", "-", "reset"), ("forward_saturation", ":", "forward")):
                if column in prog:
                    axes[4].plot(prog["frames"], 100 * prog[column], color=color, ls=style, label=f"{label}: {actor}")
        resets = run.table("resets.csv", text=("outcome",))
        if "distance_to_start" in resets:
            outcome = resets.get("outcome", np.full(len(resets["frames"]), "?"))
            for kind in [k for k in OUTCOME_MARKERS if k in outcome] + sorted(set(outcome) - set(OUTCOME_MARKERS)):
                keep = outcome == kind
                axes[3].plot(resets["frames"][keep], resets["distance_to_start"][keep], ls="none",
                             marker=OUTCOME_MARKERS.get(kind, "^"), ms=3 if kind == "success" else 4, mew=0.8,
                             alpha=0.5, color=color, label=f"{label}: {kind}")
                outcomes_seen += [] if kind in outcomes_seen else [kind]
    threshold_lines = []
    for ax in axes[:2]:  # thick and pale: told apart from the runs' thin line styles
        threshold_lines = [ax.axhline(value, color="k", lw=2.5, alpha=0.45, ls=style, label=name)
                           for (name, value), style in zip(_trigger_thresholds(algo, runs), ("-", "--", "-.", ":"))]
    check, bound = RESET_SUCCESS.get(task, ("the task's own check", None))
    bound_lines = []
    if bound is not None:
        bound_lines = [axes[3].axhline(bound, color="k", lw=2.5, alpha=0.45, label=f"reset success below {bound:g}")]
    else:  # room above the points for the note
        low, high = axes[3].get_ylim()
        axes[3].set_ylim(low, high + 0.3 * (high - low))
        _panel_note(axes[3], textwrap.fill(f"reset success: {check}, not a bound on this distance: no threshold line",
                                           48), "upper left")
    frames = tables[0][1]["frames"]
    per_row = f"{int(np.median(np.diff(frames))):,} " if len(frames) > 1 else ""  # the steps of one row (log_every)
    axes[0].set(title=f"trigger score on executed forward steps ({'p' if ours else 'Q'})", xlabel="steps",
                ylabel=score)
    axes[1].set(title=f"reset model ({'p' if ours else 'Q'}): examples, reset replay, forward replay",
                xlabel="steps", ylabel=score)
    axes[2].set(title=f"reset success rate per {stretch:,} steps" if stretch else "reset success rate",
                xlabel="steps", ylabel="successful / ended reset episodes", ylim=(-0.02, 1.02))
    axes[3].set(title="end of each reset episode: distance to the start", xlabel="steps",
                ylabel="observation distance to the start")

    def key(style="-", marker=None, label=""):  # a legend entry for a line style or marker, in no run's colour
        return Line2D([], [], color="0.3", ls=style, marker=marker, label=label)

    if saturation:
        axes[4].set(title="saturation: action components beyond 0.99 of the bound", xlabel="steps",
                    ylabel=f"% of the noiseless action's components, per {per_row}steps", ylim=(-2, 102))

    legends = [
        [key("-", label=f"mean over each {per_row}steps"), key(":", label=f"lowest in each {per_row}steps"),
         *threshold_lines],
        [key(style, label=name) for column, name, style in probes if any(column in t for _, t in tables)]
        + threshold_lines,
        [],
        [key("none", OUTCOME_MARKERS.get(kind, "^"), kind) for kind in outcomes_seen] + bound_lines,
        [key("-", label="reset actor"), key(":", label="forward actor")],
    ]
    for ax, handles in zip(axes, legends):
        ax.grid(alpha=0.3)
        if handles:
            ax.legend(handles=handles, fontsize=DIAGNOSTICS_LEGEND_SIZE, loc="upper center",
                      bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)
    fig.legend(handles=[Line2D([], [], color=c, lw=2, label=label) for c, label in zip(colors, labels)],
               loc="outside upper right", ncol=min(len(runs), 6), fontsize=DIAGNOSTICS_LEGEND_SIZE, frameon=False)
    fig.suptitle(f"{TASK_TITLES.get(task, task)}, {_title(algo, setting)}: diagnostics")
    return fig


def figure_diagnostics(runs: list[RunFolder], out: Path) -> list[Path]:
    """One diagnostics figure per task, algorithm and setting whose runs logged diagnostics
    (:func:`diagnostics_figure`)."""
    written = []
    for (task, algo, setting), members in _by(runs, "task", "algo", "setting").items():
        fig = diagnostics_figure(task, algo, setting, members)
        if fig is not None:
            _save(fig, out / f"diagnostics_{task}_{algo}{_file_suffix(setting)}.png", written)
    return written


def _curriculum_label(run: RunFolder) -> str:
    config = run.folder / "config.yaml"
    if config.exists():
        from omegaconf import OmegaConf

        label = OmegaConf.select(OmegaConf.load(config), "task.curriculum.label")
        if label:
            return str(label)
    return "observation entry before the trigger"


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
