"""The report's figures (3, 4, 5 and the diagnostics) drawn from groups of :class:`~.runs.RunFolder`:
``draw_*`` returns one figure, ``figure*`` writes every figure of its kind for a list of runs."""
from __future__ import annotations

import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from torchrl_reset_recipes.analysis.stretches import run_task
from torchrl_reset_recipes.training.reset_agents import KINDS
from torchrl_reset_recipes.analysis.runs import (TASK_TITLES, METRICS, COLORS, RunFolder, is_paper_setting, title,
                                                 file_suffix,
                                                 mean_std, reached,
                                                 complete,
                                                 row_order, by)


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
    kept, _ = complete(by(task_runs, "algo", "setting"))
    groups = {}
    for (algo, setting), members in sorted(kept.items(), key=lambda kv: row_order("", *kv[0], None)):
        label = title(algo, setting)
        key = algo + (f" ({setting})" if setting else "")
        groups[key] = (members, label if all(map(reached, members)) else f"{label}, in progress")
    return groups


def _line_style(setting: str, others: list[str]) -> str:
    """Solid for the only or the paper's setting; dashed, dotted, dash-dotted for the others in turn."""
    if is_paper_setting(setting):
        return "-"
    variants = sorted(s for s in others if not is_paper_setting(s))
    return ("--", ":", "-.")[variants.index(setting) % 3]


def _episodic_style(style: str, settings_differ: bool, plain: str = "--") -> dict:
    """Fig. 3's companion line (the resets an episodic agent would have needed; the falls in reset steps) beside
    a group drawn in ``style``: thin and ``plain`` (dashed); where settings already take the line styles, thin in
    its group's style with hollow markers, so that it is told apart from every other line of the panel."""
    if not settings_differ:
        return {"linestyle": plain, "lw": 1.2}
    return {"linestyle": style, "lw": 1.2, "marker": "o", "mfc": "none", "ms": 3.5, "markevery": 0.1}


def _config_value(run: RunFolder, key: str):

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


def draw_figure3(task: str, task_runs: list[RunFolder]):
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
    for (task,), task_runs in by(runs, "task").items():
        _save(draw_figure3(task, task_runs), out / f"fig3_{task}.png", written)
    return written


def figure4(runs: list[RunFolder], out: Path) -> list[Path]:
    written = []
    for (task, algo, setting), members in by(runs, "task", "algo", "setting").items():
        thresholds = sorted({r.p_thresh for r in members if r.p_thresh is not None})
        if len(thresholds) < 2:
            continue
        fig, axes = plt.subplots(1, 4, figsize=(14, 3.4))
        for ax, metric in zip(axes, METRICS):
            stats = [mean_std([r.summary[metric] for r in members if r.p_thresh == p]) for p in thresholds]
            ax.errorbar(thresholds, [m for m, *_ in stats], yerr=[s for _, s, *_ in stats], marker="o", capsize=3,
                        color=COLORS.get(algo))
            ax.set(xlabel="p_thresh", title=metric.replace("_", " "))
            ax.grid(alpha=0.3)
        fig.suptitle(f"{TASK_TITLES.get(task, task)}, {title(algo, setting)}: p_thresh sweep")
        _save(fig, out / f"fig4_{task}_{algo}{file_suffix(setting)}.png", written)
    return written


def _run_labels(members: list[RunFolder]) -> list[str]:
    """``seed k`` for each run, with its p_thresh where the runs differ in it."""
    sweep = len({run.p_thresh for run in members}) > 1
    return [f"seed {run.summary['seed']}" + (f", p_thresh {run.p_thresh}" if sweep else "") for run in members]


def draw_figure5(task: str, algo: str, setting: str, members: list[RunFolder]):
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
    ax.set(title=f"{TASK_TITLES.get(task, task)}, {title(algo, setting)}: state before each trigger",
           xlabel="steps (forward + reset)", ylabel=_curriculum_label(members[0]))
    ax.set_xlim(0, max(run.summary.get("steps", 0) for run in members) or None)  # the whole run, quiet stretches too
    ax.grid(alpha=0.3)
    if len(quiet) < len(members) or edge is not None:
        ax.legend(fontsize=8, markerscale=2)
    return fig


def cliff_edge(run: RunFolder) -> float | None:
    """The cliff's edge on Fig. 5's axis: the task's ``edge`` where Fig. 5 plots the x position (observation
    entry 0, the cliff tasks' curriculum), else None."""
    cfg, spec = run_task(run.folder)
    edge = getattr(getattr(spec, "env_class", None), "edge", None)
    return None if edge is None or OmegaConf.select(cfg, "task.curriculum.index") != 0 else float(edge)


def figure5(runs: list[RunFolder], out: Path) -> list[Path]:
    written = []
    for (task, algo, setting), members in by(runs, "task", "algo", "setting").items():
        _save(draw_figure5(task, algo, setting, members), out / f"fig5_{task}_{algo}{file_suffix(setting)}.png",
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
    if KINDS[algo].scores_probability:
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


def draw_diagnostics(task: str, algo: str, setting: str, members: list[RunFolder]):
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
    kind = KINDS[algo]
    probability, score = kind.scores_probability, kind.score_name
    # LNT's trigger takes the members' minimum, so the lowest member is the forward-replay line itself
    probes = [probe for probe in PROBE_SERIES if probability or probe[0] != "forward_p_min_member"]
    progress = [run.table("progress.csv") for run in runs]
    stretch = _stretch(progress)
    saturation = any("reset_saturation" in prog for prog in progress)  # runs that logged it (every run since it exists)
    # learner.mode=async runs: the learner's lag behind the actor and the age of the weights in use
    lagging = any(np.nanmax(prog.get("learner_lag_max", [0]), initial=0) > 0 for prog in progress)
    panels = 4 + saturation + lagging
    fig, axes = plt.subplots(1, panels, figsize=(4.5 * panels, 4.8), layout="constrained")
    lag_ax = axes[4 + saturation] if lagging else None
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
        if lagging:
            for column, style in (("learner_lag_mean", "-"), ("weight_age_mean", ":")):
                if column in prog:
                    lag_ax.plot(prog["frames"], prog[column], color=color, ls=style, label=f"{label}: {column}")
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
    axes[0].set(title=f"trigger score on executed forward steps ({'p' if probability else 'Q'})", xlabel="steps",
                ylabel=score)
    axes[1].set(title=f"reset model ({'p' if probability else 'Q'}): examples, reset replay, forward replay",
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
    ]
    if saturation:
        legends.append([key("-", label="reset actor"), key(":", label="forward actor")])
    if lagging:
        lag_ax.set(title="learner process: lag behind the actor, age of the weights acting", xlabel="steps",
                   ylabel=f"steps (mean over each {per_row}steps)")
        legends.append([key("-", label="lag: steps sent, not yet learnt from"),
                        key(":", label="age of the weights in use")])
    for ax, handles in zip(axes, legends):
        ax.grid(alpha=0.3)
        if handles:
            ax.legend(handles=handles, fontsize=DIAGNOSTICS_LEGEND_SIZE, loc="upper center",
                      bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)
    fig.legend(handles=[Line2D([], [], color=c, lw=2, label=label) for c, label in zip(colors, labels)],
               loc="outside upper right", ncol=min(len(runs), 6), fontsize=DIAGNOSTICS_LEGEND_SIZE, frameon=False)
    fig.suptitle(f"{TASK_TITLES.get(task, task)}, {title(algo, setting)}: diagnostics")
    return fig


def figure_diagnostics(runs: list[RunFolder], out: Path) -> list[Path]:
    """One diagnostics figure per task, algorithm and setting whose runs logged diagnostics
    (:func:`draw_diagnostics`)."""
    written = []
    for (task, algo, setting), members in by(runs, "task", "algo", "setting").items():
        fig = draw_diagnostics(task, algo, setting, members)
        if fig is not None:
            _save(fig, out / f"diagnostics_{task}_{algo}{file_suffix(setting)}.png", written)
    return written


def _curriculum_label(run: RunFolder) -> str:
    config = run.folder / "config.yaml"
    if config.exists():
        label = OmegaConf.select(OmegaConf.load(config), "task.curriculum.label")
        if label:
            return str(label)
    return "observation entry before the trigger"

