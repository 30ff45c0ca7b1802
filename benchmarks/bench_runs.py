"""Many runs in one process against separate processes, on peg-insertion (insert) at the paper's settings.

    python benchmarks/bench_runs.py                          # S = 1, 2, 5, 10; about 15 minutes on 2 cores
    python benchmarks/bench_runs.py --runs 1 5 --steps 900   # a shorter look
    python benchmarks/bench_runs.py --runs 1 5 --acting      # also each batch with speed.batched_acting=true
    python benchmarks/bench_runs.py --device cuda            # every run's networks and batches on the GPU

Side by side, in one invocation, each configuration its own process of ``recipes/train.py``
(algorithm ``ours``, 400-300 networks, batch 64 / 256 + 256 examples, K = 5, n = 10; only the
heat-up is shortened, ``--heat-up``, so that the updates start sooner: it changes no update's cost):

- **batched**: ``seeds=S`` in one process with ``--threads`` torch threads (2: the whole machine),
  for each S. Its ``summary.json`` times the iterations once every run's agents both update: the
  aggregate run-steps per second, and the time per run-step outside the update calls (env steps,
  policies, triggers, buffers, records).
- **batched, split**: the S runs as two batches of about S / 2, one process per core with one
  torch thread each (S >= 2); their aggregate rate is the sum of the two processes' rates.
- **separate**: single runs, one torch thread each, two processes at a time on the two cores, as a
  grid of S runs would go: their aggregate rate is the sum of the two processes' rates, measured
  over the same steady steps (each run's ``step_seconds`` at its own forward share). S runs take
  ``S / aggregate`` either way, so the ratio of aggregate rates is the speed-up of batching S runs.
- with ``--acting``, both batched layouts again with ``speed.batched_acting=true``: the S runs also act
  as one (one env of S copies, one policy and trigger call per phase, the exploration as one vector step).

Writes ``benchmarks/results/runs-<date>.json`` and ``.md``.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_updates import check_device, describe, machine, write_results  # noqa: E402

TASK, ALGO = "peg_insertion_insert", "ours"
GRID_RUNS, PAPER_STEPS = 90, 1_500_000  # the paper's Table 1: 6 tasks x 3 algorithms x 5 seeds, 1.5M steps each
TARGET_RATIO_S5 = 1.7  # S = 5 batched against separate processes, two CPU cores
TARGET_OUTSIDE_MS_S5 = 1.0  # per run-step outside the updates at S = 5
# the settings the committed results were measured at (batches then needed them; they run the preset now,
# docs/many-runs.md), kept so that new measurements compare with those; every layout alike: the same work per run-step
BATCH_SETTINGS = ("exploration.restart=episode", "update_order=joint")


def command(out: Path, steps: int, heat_up: int, threads: int, *, seeds=None, seed: int = 0,
            overrides: tuple[str, ...] = ()) -> list[str]:
    args = [sys.executable, str(ROOT / "recipes" / "train.py"), f"task={TASK}", f"algo={ALGO}", f"total_steps={steps}",
            f"heat_up={heat_up}", f"threads={threads}", f"sweep_dir={out}", "progress_bar=false",
            f"eval_every={10 * steps}", f"checkpoint_every={10 * steps}", f"log_every={steps}", *BATCH_SETTINGS,
            *overrides]
    return args + ([f"seeds={seeds}"] if seeds is not None else [f"seed={seed}"])


def seed_list(seeds) -> str:
    return "[" + ",".join(str(s) for s in seeds) + "]"


def summaries(out: Path, seeds) -> list[dict]:
    return [json.loads((out / TASK / ALGO / f"seed{s}" / "summary.json").read_text()) for s in seeds]


def run(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env={**os.environ, "RL_WARNINGS": "0"}, cwd=ROOT)


def wait(proc: subprocess.Popen, what: str) -> None:
    _, err = proc.communicate()
    if proc.returncode:
        raise SystemExit(f"{what} failed (exit {proc.returncode}):\n{err.decode()[-3000:]}")


def steady_rate(summary: dict) -> float:
    """A run's steps per second once both its agents update: its phases' mean step times at its forward share."""
    share, times = summary["forward_share"], summary["step_seconds"]
    if times["forward"] is None or times["reset"] is None:
        raise SystemExit("a separate run never reached steady state; give it more --steps.")
    return 1.0 / (share * times["forward"] + (1.0 - share) * times["reset"])


def measure(tmp: Path, count: int, args, overrides: tuple[str, ...], label: str, suffix: str, report: dict) -> list:
    """The batch of ``count`` runs in one process, then (``count`` >= 2, unless ``--no-split``) as two batches
    of about ``count / 2``, one process per core with one thread each: ``[(row name, entry)]``; the entries go
    into ``report["batched" + suffix]`` and ``report["split" + suffix]``."""
    key = "batched" + suffix
    out = tmp / f"{key}{count}"
    started = time.perf_counter()
    wait(run(command(out, args.steps, args.heat_up, args.threads, seeds=count, overrides=overrides)),
         f"the batch of {count}{label}")
    batch = summaries(out, range(count))
    timing = batch[0]["batch"]
    if not timing["steady_iterations"]:
        raise SystemExit(f"the batch of {count}{label} never reached steady state; give it more --steps.")
    entry = {**timing, "aggregate_run_steps_per_second": timing["run_steps_per_second"],
             "wall_seconds": time.perf_counter() - started,
             "forward_share": sum(s["forward_share"] for s in batch) / count}
    report.setdefault(key, {})[count] = entry
    rows = [(f"{count}, one process{label}", entry)]
    if count < 2 or not args.split:
        return rows
    halves = [list(range(0, (count + 1) // 2)), list(range((count + 1) // 2, count))]
    out = tmp / f"split{key}{count}"
    started = time.perf_counter()
    procs = [run(command(out, args.steps, args.heat_up, 1, seeds=seed_list(h), overrides=overrides)) for h in halves]
    for p in procs:
        wait(p, f"a half of the split batch of {count}{label}")
    parts = [summaries(out, h)[0]["batch"] for h in halves]
    if not all(t["steady_iterations"] for t in parts):
        raise SystemExit(f"the split batch of {count}{label} never reached steady state; give it more --steps.")
    split = {"runs": count, "aggregate_run_steps_per_second": sum(t["run_steps_per_second"] for t in parts),
             "outside_updates_ms_per_run_step": sum(t["outside_updates_ms_per_run_step"] * t["runs"] for t in parts) / count,
             "processes": parts, "wall_seconds": time.perf_counter() - started}
    report.setdefault("split" + suffix, {})[count] = split
    sizes = " + ".join(str(t["runs"]) for t in parts)
    return rows + [(f"{count}, two processes ({sizes}){label}", split)]


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 2, 5, 10], help="the batch sizes S")
    parser.add_argument("--steps", type=int, default=1400, help="environment steps per run (default 1400)")
    parser.add_argument("--heat-up", type=int, default=200, help="steps of each phase before its agent updates")
    parser.add_argument("--threads", type=int, default=2, help="torch threads of a batched process (default 2)")
    parser.add_argument("--no-split", dest="split", action="store_false",
                        help="leave out the two-processes-of-S/2 layout")
    parser.add_argument("--acting", action="store_true",
                        help="also each batch with speed.batched_acting=true (the runs act as one: one env of S copies)")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    parser.add_argument("--device", default="cpu",
                        help="the recipe's device for every run (cpu or cuda[:k]); the GPU's name goes in the results")
    parser.add_argument("--override", action="append", default=[],
                        help="an extra recipe setting for every run (key=value; repeatable), stated in the results")
    args = parser.parse_args(argv)
    if any(s < 1 for s in args.runs) or args.steps <= 3 * args.heat_up:
        raise SystemExit("--runs must be positive and --steps well past 3 x --heat-up (the steady part is measured).")
    device = check_device(args.device)
    info, extra = machine(device), (*args.override, f"device={device}")
    rows, report = [], {"machine": info, "task": TASK, "algo": ALGO, "steps": args.steps, "heat_up": args.heat_up,
                        "threads": args.threads, "overrides": list(extra), "batched": {}}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # separate processes: two single runs at a time, one thread each
        started = time.perf_counter()
        procs = [run(command(tmp / "separate", args.steps, args.heat_up, 1, seed=s, overrides=extra)) for s in (0, 1)]
        for p in procs:
            wait(p, "a separate run")
        alone = summaries(tmp / "separate", (0, 1))
        separate = sum(steady_rate(s) for s in alone)
        report["separate"] = {"aggregate_steps_per_second": separate, "wall_seconds": time.perf_counter() - started,
                              "runs": [{k: s[k] for k in ("seed", "device", "forward_share", "step_seconds", "steps_per_second")}
                                       for s in alone]}
        layouts = [("", "", ())] + ([(", batched acting", "_acting", ("speed.batched_acting=true",))] if args.acting else [])
        for count in args.runs:
            for label, suffix, acting in layouts:
                if acting and count < 2:
                    continue
                rows += measure(tmp, count, args, (*extra, *acting), label, suffix, report)
    lines = [f"# Many runs in one process ({info['date']})", "",
             describe(info, args.threads) + " Batched: one process, "
             f"{args.threads} torch threads; separate: single runs, 1 thread each, two processes at a time.",
             f"peg-insertion (insert), ours at the paper's settings, {args.steps} steps per run, heat-up "
             f"{args.heat_up}; rates over the steps once every run's agents both update."
             + f" Changed from the paper's settings: {', '.join((*BATCH_SETTINGS, *extra))}.", "",
             "| runs S | aggregate run-steps/s | vs separate processes | outside the updates, ms per run-step "
             "| updates, ms per iteration | mean forward share |", "|---|---|---|---|---|---|",
             f"| separate (2 processes) | {separate:.1f} | 1.00x | | | "
             f"{sum(s['forward_share'] for s in alone) / 2:.2f} |"]
    for name, entry in rows:
        entry["ratio_vs_separate"] = entry["aggregate_run_steps_per_second"] / separate
        updates = f"{entry['update_ms_per_iteration']:.1f}" if "update_ms_per_iteration" in entry else ""
        share = f"{entry['forward_share']:.2f}" if "forward_share" in entry else ""
        lines.append(f"| {name} | {entry['aggregate_run_steps_per_second']:.1f} | {entry['ratio_vs_separate']:.2f}x "
                     f"| {entry['outside_updates_ms_per_run_step']:.2f} | {updates} | {share} |")
    rates = {"separate processes": separate, **{name: entry["aggregate_run_steps_per_second"] for name, entry in rows}}
    best = max(rates, key=rates.get)
    hours = GRID_RUNS * PAPER_STEPS / rates[best] / 3600
    report["projected_table1_grid"] = {"layout": best, "run_steps_per_second": rates[best], "hours": hours}
    lines += ["", f"The paper's whole Table 1 grid ({GRID_RUNS} runs x {PAPER_STEPS:,} steps) at the best rate measured "
              f"here ({best}, {rates[best]:.1f} run-steps/s): {hours:,.0f} hours ({hours / 24:.0f} days) on this machine "
              "(peg-insertion's step costs; the other tasks' differ)."]
    checks = []
    fives = [(name, entry) for name, entry in rows if entry["runs"] == 5]
    if fives:
        best_name, best_entry = max(fives, key=lambda item: item[1]["ratio_vs_separate"])
        least = min(entry["outside_updates_ms_per_run_step"] for _, entry in fives)
        checks += [(f"S = 5 batched (the best layout: {best_name}) >= {TARGET_RATIO_S5}x separate processes",
                    f"{best_entry['ratio_vs_separate']:.2f}x", best_entry["ratio_vs_separate"] >= TARGET_RATIO_S5),
                   (f"S = 5: <= {TARGET_OUTSIDE_MS_S5} ms per run-step outside the updates (the least of its layouts)",
                    f"{least:.2f}", least <= TARGET_OUTSIDE_MS_S5)]
    if checks:
        lines += ["", "| target | measured | met |", "|---|---|---|"]
        lines += [f"| {name} | {value} | {'yes' if ok else 'NO'} |" for name, value, ok in checks]
    report["targets"] = [{"target": n, "measured": v, "met": ok} for n, v, ok in checks]
    write_results(args.out, "runs", report, "\n".join(lines) + "\n")
    return report


if __name__ == "__main__":
    main()
