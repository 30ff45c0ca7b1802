"""Frozen: its question is decided. It last ran at commit 271779f, as results/peg-early-triggers/probes/measure.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/peg-early-triggers/probes/measure.py --help``.

The protocol's measurements for each run (README: Runs), seed by seed, configurations side by side.

    python results/peg-early-triggers/probes/measure.py \\
        project_actor=runs/100k-tanh_normal_auto/peg_insertion_insert/ours \\
        release_actor=runs/peg-early-triggers/release_actor/peg_insertion_insert/ours \\
        learn_from_forward=runs/peg-early-triggers/learn_from_forward/peg_insertion_insert/ours --seeds 0-2

Each ``NAME=FOLDER`` holds ``seed<k>/`` run folders of one task: peg insertion (insert) or cliff-cheetah. For
the stretch ``--start`` to ``--end`` (default 30,000-50,000 steps) and each run: its triggers, and how many of
them stopped the forward agent at a state inside the task's at-initial-state check, worked out from the state
``triggers.csv`` logged on the task's model (peg: ``d_start < 0.2`` from the arm's joint positions, as
``../../lnt-sparse/probes/peg_check.py`` works it out; cliff-cheetah: ``|x| < 0.1`` and ``|pitch| < 0.1``, the
env's own ``reset_success`` on the body's position; where the run logged the env's flag, ``at_initial_state``,
the two are compared); the reset episodes that ended in the
stretch and the share that succeeded; and at ``--end`` (the last ``progress.csv`` row at or before it) the
manual resets and the forward share. A run that has not reached ``--end`` is listed as running. Per
configuration, the mean of the finished runs with its bootstrap 95% interval (three or more). ``--figure PNG``
also draws every run stretch by stretch (``--window`` steps, as far as it has gone): the share of its
triggers at the start and its reset episodes, configurations in colours.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from torchrl_reset_envs import CliffCheetahEnv, PegInsertionEnv
from torchrl_reset_recipes.analysis.saved_runs import run_config, run_table
from torchrl_reset_recipes.analysis.screen import bootstrap_interval, seed_runs

CHECK = 0.2  # insert task: at the initial state when d_start < 0.2


def d_start(env: PegInsertionEnv, qpos) -> float:
    """The peg's distance from its start (the check's quantity) with the arm at joint positions ``qpos``."""
    env.set_state(qpos, np.zeros(env.model.nv))
    return env.d_start()


class AtStart:
    """A task's own at-initial-state check on a state that ``triggers.csv`` logged (its ``observation`` column),
    worked out on the task's model: ``check(observation) -> bool``."""

    #: the tasks measured here: their name in the figure and their check
    TASKS = {"peg_insertion_insert": ("Peg insert", f"d_start < {CHECK}"),
             "cliff_cheetah": ("Cliff-cheetah", "|x| < 0.1 and |pitch| < 0.1")}

    def __init__(self, task: str) -> None:
        if task not in self.TASKS:
            raise SystemExit(f"a run of {task}: the checks measured here are {', '.join(self.TASKS)}'s")
        self.task, (self.title, self.rule) = task, self.TASKS[task]
        self.env = PegInsertionEnv("insert") if task == "peg_insertion_insert" else CliffCheetahEnv()
        self.env.reset(seed=0)

    def __call__(self, observation: str) -> bool:
        values = np.array(observation.split(), dtype=float)
        if self.task == "peg_insertion_insert":
            return d_start(self.env, values[:7]) < CHECK
        self.env.data.qpos[:] = values[: self.env.model.nq]  # the observation starts with the positions
        return bool(self.env._status(None)[0])  # the env's reset_success


def measure(check: AtStart, run: Path, start: int, end: int) -> dict:
    cfg = run_config(run)
    if cfg.task.name != check.task:
        raise SystemExit(f"{run} is a run of {cfg.task.name}, the others of {check.task}: one task at a time")
    progress = [r for r in run_table(run, "progress.csv") if int(r["frames"]) <= end]
    row = {"run": str(run), "reached": int(progress[-1]["frames"]) if progress else 0}
    if row["reached"] < end:
        return row
    triggers = [t for t in run_table(run, "triggers.csv") if start < int(t["frames"]) <= end]
    inside = [check(t["observation"]) for t in triggers]
    logged = [t.get("at_initial_state", "") for t in triggers]
    resets = [r for r in run_table(run, "resets.csv") if start < int(r["frames"]) <= end]
    # a reset episode that a trigger began starts at the trigger's step (its end minus its steps)
    begun_inside = {int(t["frames"]): i for t, i in zip(triggers, inside)}
    after = {True: [], False: []}
    for r in resets:
        where = begun_inside.get(int(r["frames"]) - int(r["steps"]))
        if where is not None:
            after[where].append(r["outcome"] == "success")
    row.update(triggers=len(triggers), inside=float(np.mean(inside)) if inside else float("nan"),
               env_flag_agrees=(None if "" in logged or not logged else
                                sum(int(f) == i for f, i in zip(logged, inside)) / len(logged)),
               reset_episodes=len(resets),
               reset_success=float(np.mean([r["outcome"] == "success" for r in resets])) if resets else float("nan"),
               manual_resets=int(progress[-1]["manual_resets"]), forward_share=float(progress[-1]["forward_share"]),
               after_inside=after[True], after_outside=after[False])
    return row


def by_stretch(check: AtStart, run: Path, window: int) -> tuple[list[int], list[float], list[int]]:
    """Per stretch of ``window`` steps that ``progress.csv`` has reached: its end, the share of its triggers
    inside the check (NaN without a trigger) and the reset episodes that ended in it."""
    reached = max((int(r["frames"]) for r in run_table(run, "progress.csv")), default=0)
    triggers = [(int(t["frames"]), check(t["observation"])) for t in run_table(run, "triggers.csv")]
    ends = [int(r["frames"]) for r in run_table(run, "resets.csv")]
    stops, shares, resets = [], [], []
    for stop in range(window, reached + 1, window):
        inside = [i for f, i in triggers if stop - window < f <= stop]
        stops.append(stop)
        shares.append(float(np.mean(inside)) if inside else float("nan"))
        resets.append(sum(stop - window < e <= stop for e in ends))
    return stops, shares, resets


def figure(check: AtStart, runs: dict[str, list[Path]], window: int):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7.5, 6.0), sharex=True)
    for i, (name, folders) in enumerate(runs.items()):
        for k, run in enumerate(folders):
            stops, shares, resets = by_stretch(check, run, window)
            x = [s / 1000 for s in stops]
            label = name if k == 0 else None
            top.plot(x, [100 * v for v in shares], marker="o", markersize=3, color=f"C{i}", alpha=0.8, label=label)
            bottom.plot(x, resets, marker="o", markersize=3, color=f"C{i}", alpha=0.8, label=label)
    top.set_ylabel(f"triggers at the start (%)\nper {window // 1000}k steps")
    bottom.set_ylabel(f"reset episodes\nper {window // 1000}k steps")
    bottom.set_xlabel("steps (thousands), at the end of each stretch")
    top.legend(fontsize=8)
    top.set_title(f"{check.title}: where the trigger stops the forward agent ({check.rule}: already at the start)",
                  fontsize=9)
    fig.tight_layout()
    return fig


def _cell(values, share: bool) -> str:
    mean, low, high = bootstrap_interval(values)
    show = (lambda v: f"{100 * v:.0f}%") if share else (lambda v: f"{v:.0f}")
    if mean != mean:
        return "n/a"
    return show(mean) + ("" if low != low else f" [{show(low)}, {show(high)}]")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("configurations", nargs="+", help="NAME=FOLDER, FOLDER holding seed<k>/ run folders")
    parser.add_argument("--seeds", default="0-2")
    parser.add_argument("--start", type=int, default=30000)
    parser.add_argument("--end", type=int, default=50000)
    parser.add_argument("--figure", type=Path, default=None, help="a PNG of every run stretch by stretch")
    parser.add_argument("--window", type=int, default=10000, help="the figure's stretch in steps (default 10,000)")
    args = parser.parse_args(argv)
    if args.window < 1:
        parser.error("--window must be a positive number of steps")
    if not 0 <= args.start < args.end:
        parser.error("the stretch needs 0 <= --start < --end")
    check = None  # the first run's task's
    stretch = f"{args.start // 1000}-{args.end // 1000}k"
    print(f"| configuration | seed | triggers {stretch} | inside the check | reset episodes {stretch} | reset success "
          f"{stretch} | manual resets at {args.end // 1000}k | forward share |")
    print("|---|---|---|---|---|---|---|---|")
    finished, started = {}, {}
    try:
        runs = seed_runs(args.configurations, args.seeds)
    except ValueError as err:
        parser.error(str(err))
    for name, seed, run in runs:
        if not (run / "config.yaml").exists():
            print(f"| {name} | {seed} | not started | | | | | |")
            continue
        started.setdefault(name, []).append(run)
        if check is None:
            check = AtStart(run_config(run).task.name)
        r = measure(check, run, args.start, args.end)
        if "triggers" not in r:
            print(f"| {name} | {seed} | running (at {r['reached']}) | | | | | |")
            continue
        finished.setdefault(name, []).append(r)
        agrees = "" if r["env_flag_agrees"] is None else f" (env's flag agrees on {100 * r['env_flag_agrees']:.0f}%)"
        print(f"| {name} | {seed} | {r['triggers']} | {100 * r['inside']:.0f}%{agrees} | {r['reset_episodes']} | "
              f"{100 * r['reset_success']:.0f}% | {r['manual_resets']} | {r['forward_share']:.2f} |")
    print()
    print(f"Reset episodes begun by a trigger in {stretch}, by where the trigger fired:")
    print("| configuration | seed | begun inside the check | of them successful | begun outside | of them successful |")
    print("|---|---|---|---|---|---|")
    share = lambda outcomes: f"{100 * np.mean(outcomes):.0f}%" if outcomes else "-"  # noqa: E731
    for name, rows in finished.items():
        for r in rows:
            print(f"| {name} | {Path(r['run']).name.removeprefix('seed')} | {len(r['after_inside'])} | {share(r['after_inside'])} | "
                  f"{len(r['after_outside'])} | {share(r['after_outside'])} |")
    print()
    print("| configuration | runs | inside the check | reset success | manual resets | forward share |")
    print("|---|---|---|---|---|---|")
    for name, rows in finished.items():
        print(f"| {name} | {len(rows)} | {_cell([r['inside'] for r in rows], True)} | "
              f"{_cell([r['reset_success'] for r in rows], True)} | {_cell([r['manual_resets'] for r in rows], False)} | "
              f"{_cell([r['forward_share'] for r in rows], True)} |")
    if args.figure is not None and check is None:
        print(f"no run has started: no {args.figure}")
    elif args.figure is not None:
        figure(check, started, args.window).savefig(args.figure, dpi=120)
        print(f"wrote {args.figure}")


if __name__ == "__main__":
    main()
