"""The cost of acting per run-step: S runs each with its own collector, against one batched collector.

    python benchmarks/bench_acting.py                        # S = 1, 5, 10; about 2 minutes on one core
    python benchmarks/bench_acting.py --runs 1 5 --steps 300 # a shorter look
    python benchmarks/bench_acting.py --device cuda          # networks and the environments' output on the GPU

Everything a run does per environment step except the updates and the replay buffers: the
environment step (peg-insertion (insert)), the forward or reset policy with its Ornstein-Uhlenbeck
exploration, the trigger (K = 5 classifiers with randomized priors on the forward action) and
Algorithm 1's bookkeeping, at the paper's network sizes (400-300). Side by side in one invocation,
on the same S runs' networks:

- **separate**: one :class:`~torchrl_reset.DualCollector` per run, stepped in turn (what a batch of
  runs does today, and what each separate process does);
- **batched**: one :class:`~torchrl_reset.BatchedDualCollector` over a
  :class:`~torchrl_reset_envs.BatchedTaskEnv` of S copies, the S runs' policies and ensembles as
  one module each (:meth:`~torchrl_reset.many.RunPolicies.module`,
  :meth:`~torchrl_reset.many.RunEnsembles.module`).

Prints milliseconds per run-step (wall time over executed steps of all runs) and the ratio; writes
``benchmarks/results/acting-<date>.json`` and ``.md``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs import TransformedEnv
from torchrl.modules import OrnsteinUhlenbeckProcessModule

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "recipes"))

from agents import make_actor  # noqa: E402
from bench_updates import check_device, describe, machine, synchronizer, write_results  # noqa: E402

from torchrl_reset import DualCollector, EnsembleValueOperator, ResetTriggerTransform  # noqa: E402
from torchrl_reset.many import BatchedDualCollector, RowResetTriggerTransform  # noqa: E402
from torchrl_reset.many import RunEnsembles, RunPolicies  # noqa: E402
from torchrl_reset_envs import BatchedTaskEnv, make_env  # noqa: E402

TASK, HIDDEN, MEMBERS, PRIOR, P_THRESH, H_F, H_R = "peg_insertion_insert", (400, 300), 5, 3.0, 0.1, 100, 200


def explore(module, spec):
    return TensorDictSequential(module, OrnsteinUhlenbeckProcessModule(spec=spec, eps_init=1.0, eps_end=1.0, annealing_num_steps=1))


def networks(runs: int, obs_dim: int, spec, device: str = "cpu"):
    torch.manual_seed(0)
    forward = [make_actor(obs_dim, spec, HIDDEN).to(device) for _ in range(runs)]
    reset = [make_actor(obs_dim, spec, HIDDEN).to(device) for _ in range(runs)]
    ensembles = [EnsembleValueOperator(obs_dim, spec.shape[-1], num_members=MEMBERS, hidden_sizes=HIDDEN,
                                       prior_scale=PRIOR).to(device) for _ in range(runs)]
    return forward, reset, ensembles


def timed(collector, steps_total: int, warm_up: int, device: str = "cpu") -> float:
    """Seconds per executed step over ``steps_total`` steps after ``warm_up`` (all runs' steps together),
    up to the end of the device's queued work."""
    sync, done, started = synchronizer(device), 0, None
    for batch in collector:
        done += batch.shape[0]
        if started is None and done >= warm_up:
            sync()
            started, done = time.perf_counter(), 0
        elif started is not None and done >= steps_total:
            break
    sync()
    return (time.perf_counter() - started) / done


def separate(runs: int, steps: int, warm_up: int, device: str = "cpu") -> float:
    probe = make_env(TASK, seed=0, device=device)
    obs_dim, spec = probe.observation_spec["observation"].shape[-1], probe.action_spec
    forward, reset, ensembles = networks(runs, obs_dim, spec, device)
    collectors = []
    for s in range(runs):
        env = make_env(TASK, seed=s, device=device)
        env.append_transform(ResetTriggerTransform(ensembles[s], P_THRESH))
        collectors.append(iter(DualCollector(env, explore(forward[s], spec), explore(reset[s], spec),
                                             max_forward_steps=H_F, max_reset_steps=H_R)))

    def lockstep():  # one step of each run in turn, as a batch of runs with one collector each
        while True:
            for c in collectors:
                yield next(c)

    return timed(lockstep(), steps * runs, warm_up * runs, device)


def batched(runs: int, steps: int, warm_up: int, device: str = "cpu") -> float:
    base = BatchedTaskEnv(TASK, seeds=list(range(runs)), device=device)
    obs_dim, spec = base.observation_spec["observation"].shape[-1], make_env(TASK, device=device).action_spec
    forward, reset, ensembles = networks(runs, obs_dim, spec, device)
    policies = [explore(RunPolicies(group).module(), base.action_spec) for group in (forward, reset)]
    trigger = RowResetTriggerTransform(RunEnsembles(ensembles).module(), P_THRESH)
    collector = BatchedDualCollector(TransformedEnv(base, trigger), *policies, max_forward_steps=H_F, max_reset_steps=H_R)
    return timed(collector, steps * runs, warm_up * runs, device)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, nargs="+", default=[1, 5, 10])
    parser.add_argument("--steps", type=int, default=1000, help="timed steps per run")
    parser.add_argument("--warm-up", type=int, default=100, help="untimed steps per run first")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu", help="cpu or cuda[:k]: networks and the environments' output there")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = parser.parse_args(argv)
    device = check_device(args.device)
    torch.set_num_threads(args.threads)
    rows = []
    for runs in args.runs:
        sep, bat = separate(runs, args.steps, args.warm_up, device), batched(runs, args.steps, args.warm_up, device)
        rows.append({"runs": runs, "separate_ms_per_run_step": 1e3 * sep, "batched_ms_per_run_step": 1e3 * bat,
                     "speedup": sep / bat})
        print(f"S = {runs}: separate {1e3 * sep:.2f} ms, batched {1e3 * bat:.2f} ms per run-step ({sep / bat:.2f}x)", flush=True)
    report = {"machine": machine(device), "threads": args.threads, "steps_per_run": args.steps, "task": TASK, "rows": rows}
    lines = [f"# Acting per run-step: separate collectors against one batched collector ({TASK})", "",
             f"{args.threads} torch thread(s); {args.steps} timed steps per run after {args.warm_up}; 400-300 networks, "
             f"K = {MEMBERS} classifiers with priors; no updates, no replay buffers.", "",
             describe(report["machine"], args.threads), "",
             "| S | separate, ms per run-step | batched, ms per run-step | batched speed-up |", "|---|---|---|---|"]
    lines += [f"| {r['runs']} | {r['separate_ms_per_run_step']:.2f} | {r['batched_ms_per_run_step']:.2f} | {r['speedup']:.2f}x |"
              for r in rows]
    write_results(args.out, "acting", report, "\n".join(lines) + "\n")
    return report


if __name__ == "__main__":
    main()
