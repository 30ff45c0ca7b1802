"""The runs a report reads: each run folder's summary, config and tables (:class:`RunFolder`, :func:`find_runs`),
the settings that set one group of runs apart from another, how runs are grouped and summed up over seeds, and
the titles, colours and paper numbers of the report's tables and figures."""
from __future__ import annotations

import csv
import functools
import json
import math
import re
from collections import defaultdict
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from torchrl_reset_recipes import CONF
from torchrl_reset_recipes.training.absent_keys import ABSENT_KEYS
from torchrl_reset_recipes.training.reset_agents import KINDS
from torchrl_reset_envs import TASKS



#: The paper's Table 1 (1.5M steps, mean of 5 seeds): return, manual resets, forward share, success rate (the
#: task registry's rows, ``torchrl_reset_envs.TASKS``)
PAPER_TABLE1 = {(task, algo): row for task, spec in TASKS.items() for algo, row in spec.paper.items()}

#: tables' and figures' names: tasks from the task registry, algorithms from the algorithm registry (``KINDS``)
TASK_TITLES = {task: spec.title for task, spec in TASKS.items() if spec.paper}
ALGO_TITLES = {algo: kind.title for algo, kind in KINDS.items()}
COLORS = {algo: kind.color for algo, kind in KINDS.items()}


METRICS = ("average_return", "manual_resets", "forward_share", "reset_success_rate")


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



def bootstrap_interval(values, confidence: float = 0.95) -> tuple[float, float, float]:
    """``(mean, low, high)``: the mean and its bootstrap interval (BCa, 10,000 resamples, fixed seed), NaN
    values left out; the interval is NaN below three values and collapses to the mean when all are equal."""
    from scipy.stats import bootstrap

    data = np.asarray([v for v in values if not math.isnan(v)], dtype=float)
    if data.size == 0:
        return math.nan, math.nan, math.nan
    mean = float(data.mean())
    if data.size < 3:
        return mean, math.nan, math.nan
    if np.all(data == data[0]):
        return mean, mean, mean
    result = bootstrap((data,), np.mean, confidence_level=confidence, n_resamples=10_000, method="BCa",
                       rng=np.random.default_rng(0))
    low, high = result.confidence_interval
    return mean, float(low), float(high)


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval of a success share ``successes / n`` (95% at z = 1.96); NaN for ``n = 0``.
    Unlike the normal approximation it stays inside [0, 1] and is not empty at 0 or n successes."""
    if n == 0:
        return math.nan, math.nan
    p = successes / n
    centre, half = p + z * z / (2 * n), z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return (centre - half) / (1 + z * z / n), (centre + half) / (1 + z * z / n)


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
    if task not in TASKS or not (CONF / "algo" / f"{algo}.yaml").exists():
        return {}
    from omegaconf import OmegaConf

    from torchrl_reset_recipes.training.hydra_config import compose

    cfg = compose(["preset=paper", f"task={task}", f"algo={algo}"])
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
    for (task, algo), members in by(runs, "task", "algo").items():
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
    for (source, task, algo), members in sorted(by([r for r in runs if r.source], "source", "task", "algo").items()):
        defaults = recipe_defaults(task, algo)
        changed = sorted({f"{k}={_value_text(own[k])}" for own in (run_settings(r, defaults) for r in members)
                          for k in own if defaults and k in defaults and repr(own[k]) != repr(defaults[k])
                          and not any(k == n or k.startswith(f"{n}.") for n in NOT_A_SETTING)})
        lines.append(f"- {source}, {TASK_TITLES.get(task, task)}, {ALGO_TITLES.get(algo, algo)}: "
                     + (", ".join(changed) if changed else "the paper preset's settings"))
    return lines


def is_paper_setting(setting: str) -> bool:
    """The only setting of its group, or the recipe's defaults (the paper's)."""
    return setting in ("", PAPER_SETTING)


def title(algo: str, setting: str) -> str:
    return ALGO_TITLES.get(algo, algo) + (f" ({setting})" if setting else "")


def file_suffix(setting: str) -> str:
    """``""`` for the only or the paper's setting, else the setting as a file-name part."""
    if is_paper_setting(setting):
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


def mean_std(values: list[float]) -> tuple[float, float, float, float]:
    """Mean, population standard deviation and, over three or more values, the mean's bootstrap 95% interval
    (:func:`bootstrap_interval`; NaN below three)."""
    values = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    if not values:
        return math.nan, math.nan, math.nan, math.nan
    _, low, high = bootstrap_interval(values)
    return float(np.mean(values)), float(np.std(values)) if len(values) > 1 else 0.0, low, high


def reached(run: RunFolder) -> bool:
    return run.budget is None or run.summary.get("steps", 0) >= run.budget


def complete(groups: dict) -> tuple[dict, list[RunFolder]]:
    """With a budget, each group's runs that reached it; runs short of it are left out of the means
    (listed apart) unless no run of their group reached it (the row is then marked in progress)."""
    kept, short = {}, []
    for key, members in groups.items():
        done = [r for r in members if reached(r)]
        kept[key] = done or members
        short += [r for r in members if not reached(r)] if done else []
    return kept, short


def row_order(task: str, algo: str, setting: str, p_thresh) -> tuple:
    order = list(TASK_TITLES)
    return (order.index(task) if task in order else 99, algo, not is_paper_setting(setting), setting,
            p_thresh or 0)


def by(runs: list[RunFolder], *attributes: str) -> dict[tuple, list[RunFolder]]:
    groups = defaultdict(list)
    for run in runs:
        groups[tuple(getattr(run, a) for a in attributes)].append(run)
    return groups

