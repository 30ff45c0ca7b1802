"""Where a training run's time goes: one run of the recipe, step by step, with each part of a step timed.

    python benchmarks/profile_run.py                                  # peg insert, ours, 5k steps, 1 thread
    python benchmarks/profile_run.py --task ball_in_cup_throw --steps 3000 -- algo=lnt   # any recipe override

Builds the run exactly as ``recipes/train.py`` does (``run_spec``, ``build_run``: the paper's sizes, the
project's reset actor, the same loop and ``update``) into a temporary folder, and times, with
``time.perf_counter`` around each call (no sampling profiler, so nothing is slowed):

- **reset update** / **forward update**: ``update`` for each agent (loss, backward, optimizer, targets);
- **reset sample** / **forward sample**: the replay sample and its completion (examples, n-step flags);
- **acting**, split into the **env** (the base env's ``_step`` / ``_reset``: MuJoCo and its observation),
  the **trigger** (the classifiers scoring the forward action), the **policies** (actor and noise) and the
  collector's own bookkeeping (the remainder: tensordict copies, transforms, episode logic);
- **store** (the replay buffers' ``extend``), **record** (the per-step records), **log rows**,
  **evaluation** and **checkpoints** (each timed per event as well, so that a 100k run's share can be
  projected: evaluations every ``eval_every``, checkpoints every ``checkpoint_every``);
- **loop**: what is left of the wall time (the loop's own Python).

Prints the table and writes it with a JSON file to ``benchmarks/results/profile-<task>-<date>.md/.json``.
The run's own numbers (counters, losses) are those of the same command through ``recipes/train.py``.
"""
from __future__ import annotations

import argparse
import functools
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]

try:  # imported from the benchmarks package (the tests)
    from .bench_updates import describe, machine, write_results
except ImportError:  # run as a script
    from bench_updates import describe, machine, write_results

__all__ = ["Timers", "profile", "main"]


class Timers:
    """Named wall-clock totals and call counts; ``wrap(obj, name, bucket)`` times ``obj.name`` in place."""

    def __init__(self) -> None:
        self.total: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self.open: list[str] = []  # the spans under way, outermost first

    def add(self, bucket: str, seconds: float) -> None:
        self.total[bucket] += seconds
        self.calls[bucket] += 1

    def timed(self, bucket: str):
        timers = self

        class _Span:
            def __enter__(self):
                timers.open.append(bucket)
                self.start = time.perf_counter()

            def __exit__(self, *exc):
                timers.add(bucket, time.perf_counter() - self.start)
                timers.open.pop()

        return _Span()

    def wrap(self, obj, name: str, bucket: str, *, inside: str | None = None) -> None:
        """Times ``obj.name`` into ``bucket``; with ``inside``, only the calls made within a span of that name
        (the reset actor both acts and serves the reset update: only its acting is the policy's time)."""
        original = getattr(obj, name)

        @functools.wraps(original)
        def timed(*args, **kwargs):
            if inside is not None and inside not in self.open:
                return original(*args, **kwargs)
            start = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                self.add(bucket, time.perf_counter() - start)

        setattr(obj, name, timed)


def _base_env(env):
    from torchrl.envs import TransformedEnv

    while isinstance(env, TransformedEnv):
        env = env.base_env
    return env


def profile(overrides: list[str], steps: int, threads: int) -> dict:
    """Runs ``steps`` steps of the recipe with ``overrides`` and returns the timed parts (seconds, calls)."""
    from torchrl_reset import DualCollector
    from torchrl_reset_recipes.training.hydra_config import compose
    from torchrl_reset_recipes.training.run_spec import run_spec
    from torchrl_reset_recipes.training.single_run import build_run, set_up_process
    from torchrl_reset_recipes.training.updates import update

    with tempfile.TemporaryDirectory() as folder:
        cfg = compose([f"total_steps={steps}", f"threads={threads}", "progress_bar=false", f"run_dir={folder}/run",
                       *overrides])
        Path(cfg.run_dir).mkdir(parents=True)
        spec = run_spec(cfg)
        run = build_run(spec, set_up_process(spec))
        timers = Timers()
        env = _base_env(run.env)
        timers.wrap(env, "_step", "acting: env")
        timers.wrap(env, "_reset", "acting: env")
        timers.wrap(run.trigger, "evaluate", "acting: trigger")
        for policy in (run.collector.forward_policy, run.collector.reset_policy):
            timers.wrap(policy, "forward", "acting: policies", inside="acting")
        for name in ("step", "log", "evaluation"):
            timers.wrap(run.record, name, {"step": "record", "log": "log rows", "evaluation": "evaluation"}[name])
        timers.wrap(run, "evaluation", "evaluation")
        timers.wrap(run.state, "save", "checkpoints")
        collector, learner = run.collector, run.learner
        started = time.perf_counter()
        iterator, streams = iter(collector), run.streams
        while True:
            with timers.timed("acting"), streams.use("actor"):
                batch = next(iterator, None)
            if batch is None:
                break
            phase = DualCollector.phase_of(batch)
            agent = learner.agents[phase]
            with streams.use("learner"):
                with timers.timed("store"):
                    learner.store(batch, phase)
                for _ in range(batch.numel() if learner.updating(phase) else 0):
                    with timers.timed(f"{phase} sample"):
                        sample = learner.sample(phase)
                    with timers.timed(f"{phase} update"), learner.timed(phase):
                        losses = update(agent, sample, learner.losses[phase], release_order=learner.release_order)
                    learner.record_losses(phase, losses)
            run.after_step(batch, phase)
        run.record.close()
        summary = run.finish(False)
        wall = time.perf_counter() - started
    counters = {key: int(value) for key, value in collector.counters.items()}
    return {"overrides": overrides, "steps": steps, "threads": threads, "wall": wall, "counters": counters,
            "total": dict(timers.total), "calls": dict(timers.calls),
            "eval_every": int(cfg.eval_every), "checkpoint_every": int(cfg.checkpoint_every),
            "log_every": int(cfg.log_every), "manual_resets": summary["manual_resets"]}


ORDER = ["reset update", "forward update", "reset sample", "forward sample", "acting: env", "acting: trigger",
         "acting: policies", "acting: collector", "store", "record", "log rows", "evaluation", "checkpoints", "loop"]


def table(result: dict, projected_steps: int = 100_000) -> tuple[str, dict]:
    """The profile as a markdown table: each part's seconds, share of the wall time, ms per step, and its
    share in a ``projected_steps`` run (evaluations and checkpoints counted at their period)."""
    total, calls, steps, wall = dict(result["total"]), result["calls"], result["steps"], result["wall"]
    acting = total.pop("acting", 0.0)
    total["acting: collector"] = acting - sum(total.get(k, 0.0) for k in ORDER if k.startswith("acting: ")
                                               and k != "acting: collector")
    total["loop"] = wall - acting - sum(v for k, v in total.items() if not k.startswith("acting"))
    # per-step parts scale with steps; evaluations and checkpoints are events, projected at their period
    per_event = {k: total.get(k, 0.0) / calls[k] for k in ("evaluation", "checkpoints") if calls.get(k)}
    projected = {k: v / steps * projected_steps for k, v in total.items() if k not in per_event}
    for key, every in (("evaluation", result["eval_every"]), ("checkpoints", result["checkpoint_every"])):
        if key in per_event:
            projected[key] = per_event[key] * (projected_steps // every + (key == "checkpoints"))
    projected_wall = sum(projected.values())
    updates = total.get("reset update", 0.0) + total.get("forward update", 0.0)
    rows = ["| part | seconds | share of wall time | ms per step | calls | share in a "
            f"{projected_steps:,}-step run |", "|---|---|---|---|---|---|"]
    for key in ORDER:
        if key not in total:
            continue
        rows.append(f"| {key} | {total[key]:.1f} | {100 * total[key] / wall:.1f}% | {1000 * total[key] / steps:.2f} "
                    f"| {calls.get(key, '')} | {100 * projected.get(key, 0.0) / projected_wall:.1f}% |")
    outside = 1 - updates / wall
    outside_projected = 1 - (projected.get("reset update", 0) + projected.get("forward update", 0)) / projected_wall
    text = "\n".join(rows) + (
        f"\n\nWall time {wall:.1f} s for {steps:,} steps ({1000 * wall / steps:.1f} ms per step); outside the two "
        f"updates: {100 * outside:.1f}% here, {100 * outside_projected:.1f}% projected over {projected_steps:,} steps "
        f"({projected_wall / 3600:.2f} h). Per event: "
        + ", ".join(f"{k} {v:.2f} s" for k, v in per_event.items()) + ".")
    return text, {"parts": total, "projected": projected, "outside_updates": outside,
                  "outside_updates_projected": outside_projected, "projected_hours": projected_wall / 3600}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="peg_insertion_insert")
    parser.add_argument("--steps", type=int, default=5000)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results", help="where the files go")
    parser.add_argument("--no-write", action="store_true", help="print only")
    parser.add_argument("overrides", nargs="*", help="recipe overrides (after --), e.g. algo=lnt seed=1")
    args = parser.parse_args(argv)
    if args.steps < 1:
        parser.error(f"--steps must be at least 1, got {args.steps}")
    overrides = [f"task={args.task}", *args.overrides]
    result = profile(overrides, args.steps, args.threads)
    info = machine()
    text, derived = table(result)
    text = (f"# Where a run's time goes: {' '.join(overrides)}, {args.steps:,} steps\n\n{describe(info, args.threads)}\n"
            f"Command: `python benchmarks/profile_run.py --task {args.task} --steps {args.steps} --threads {args.threads}"
            + (f" -- {' '.join(args.overrides)}" if args.overrides else "") + "`\n\n"
            f"Counters: {result['counters']}\n\n" + text + "\n")
    report = {"machine": info, **result, **derived}
    if args.no_write:
        print(text)
    else:
        write_results(args.out, f"profile-{args.task}", report, text)
    return report


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
