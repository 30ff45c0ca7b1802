"""Frozen: its question is decided. It last ran at commit 271779f, as results/lnt-sparse/probes/peg_check.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/lnt-sparse/probes/peg_check.py --help``.

How loose is peg-insertion (insert)'s at-initial-state check, ``d_start < 0.2``?

LNT-sparse's reward is this check (1 where it holds, else 0). The more of the states the agents visit pass
it, the denser that "sparse" reward is. This probe measures, on the task's own model:

1. the check's size against the task: ``d_start`` (the 6-vector distance of the peg's two ends from their
   start positions) between the start and the goal, and the share of uniformly drawn joint positions (within
   the joints' ranges, at rest) that pass it;
2. what exploration alone does from the start: ``--episodes`` forward episodes of H_f = 100 steps from the
   start under (a) the recipe's Ornstein-Uhlenbeck noise around a zero policy (theta 0.15, sigma 0.2,
   dt 0.05), (b) uniform random actions, (c) a saturated policy holding one corner of the action box:
   the share of their end states that pass the check (a reset from there is over after the 5 minimum steps)
   and how far they get;
3. the trigger states of committed 100k runs (``--runs``, folders with ``triggers.csv``): the share already
   inside the check, in all and (``--window``) stretch by stretch.

    python results/lnt-sparse/probes/peg_check.py --episodes 50 \\
        --runs results/table1-peg-insert/peg_insertion_insert/*/seed*
    python results/lnt-sparse/probes/peg_check.py --episodes 2 --samples 20 --window 10000 \\
        --runs results/table1-peg-insert/peg_insertion_insert/ours/seed0 results/reset-actor-paper-sizes/peg_insertion_insert/ours/seed0
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from torchrl.data import Bounded
from torchrl.modules import OrnsteinUhlenbeckProcessModule

from torchrl_reset_envs import PegInsertionEnv
from torchrl_reset_envs.peg import PEG_GOAL, PEG_START, _RANGES

from torchrl_reset_recipes.analysis.runs import recipe_defaults
from torchrl_reset_recipes.analysis.saved_runs import CarriedNoise, run_table

CHECK = 0.2  # insert task: at the initial state when d_start < 0.2


def ou_actions(steps: int, dim: int) -> np.ndarray:
    """The recipe's Ornstein-Uhlenbeck noise (torchrl's module with the recipe's ``exploration`` settings for this
    task) added to a zero policy, started at zero; its draws come from torch's global generator."""
    settings = recipe_defaults("peg_insertion_insert", "lnt_sparse")
    noise = OrnsteinUhlenbeckProcessModule(
        spec=Bounded(-1.0, 1.0, (dim,)), eps_init=1.0, eps_end=1.0, annealing_num_steps=1, safe=False,
        theta=settings["exploration.theta"], sigma=settings["exploration.sigma"], dt=settings["exploration.dt"])
    noise = CarriedNoise(noise)  # fed one action at a time, as the collector feeds it
    return np.array([noise(torch.zeros(dim)).numpy() for _ in range(steps)])


def rollout(env: PegInsertionEnv, actions: np.ndarray) -> tuple[float, float, float]:
    """From the start: (d_start at the end, the largest d_start, the share of steps inside the check)."""
    env.reset()
    d, inside = [], 0
    for action in actions:
        env.step(np.clip(action, -1.0, 1.0))
        d.append(env.d_start())
        inside += d[-1] < CHECK
    return d[-1], max(d), inside / len(actions)


def at_rest(env: PegInsertionEnv, qpos) -> float:
    """d_start with the arm at rest at joint positions ``qpos`` (kinematics only)."""
    env.set_state(qpos, np.zeros(env.model.nv))
    return env.d_start()


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("--episodes", type=int, default=50, help="episodes per exploration kind (default 50)")
    parser.add_argument("--samples", type=int, default=20000, help="joint positions drawn for part 1 (default 20,000)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--runs", type=Path, nargs="*", default=[], help="run folders with triggers.csv (part 3)")
    parser.add_argument("--window", type=int, default=None,
                        help="part 3 also stretch by stretch: the triggers logged in each WINDOW steps")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    torch.manual_seed(args.seed)  # the noise module's draws
    env = PegInsertionEnv("insert")
    env.reset(seed=args.seed)

    print("1. the check against the task")
    print(f"   d_start between the start and the goal: {np.linalg.norm(PEG_GOAL - PEG_START):.3f} (the check: < {CHECK})")
    low, high = np.array([r[0] for r in _RANGES]), np.array([r[1] for r in _RANGES])
    draws = [at_rest(env, rng.uniform(low, high)) for _ in range(args.samples)]
    print(f"   joint positions drawn uniformly in the joints' ranges: {np.mean(np.array(draws) < CHECK):.2%} pass "
          f"({args.samples} draws; median d_start {np.median(draws):.2f})")

    print(f"2. exploration from the start, {args.episodes} forward episodes of 100 steps each")
    kinds = {
        "OU noise around a zero policy": lambda: ou_actions(100, 7),
        "uniform random actions": lambda: rng.uniform(-1, 1, (100, 7)),
        "one corner of the action box held": lambda: np.tile(rng.choice([-1.0, 1.0], 7), (100, 1)),
    }
    for name, draw in kinds.items():
        results = np.array([rollout(env, draw()) for _ in range(args.episodes)])
        print(f"   {name}: end inside the check {np.mean(results[:, 0] < CHECK):.0%}; end d_start median "
              f"{np.median(results[:, 0]):.2f} (max {results[:, 0].max():.2f}); farthest in the episode median "
              f"{np.median(results[:, 1]):.2f}; steps inside the check {results[:, 2].mean():.0%}")

    if args.runs:
        print("3. trigger states of the runs (the forward episode's state the trigger stopped)")
    for folder in args.runs:
        if not (folder / "triggers.csv").exists():
            continue
        states = [np.array(r["observation"].split(), dtype=float) for r in run_table(folder, "triggers.csv")]
        if not states:
            print(f"   {folder}: no trigger")
            continue
        d = np.array([at_rest(env, s[:7]) for s in states])
        print(f"   {folder}: {len(d)} triggers, {np.mean(d < CHECK):.0%} already inside the check; "
              f"d_start median {np.median(d):.2f}")
        if args.window:
            frames = np.array([int(r["frames"]) for r in run_table(folder, "triggers.csv")])
            stretch = (frames - 1).clip(min=0) // args.window  # a trigger logged at step t lies in (lo, lo + window]
            for k in np.unique(stretch):
                inside = d[stretch == k]
                print(f"     {k * args.window}-{(k + 1) * args.window}: {inside.size} triggers, "
                      f"{np.mean(inside < CHECK):.0%} inside the check, d_start median {np.median(inside):.2f}")


if __name__ == "__main__":
    main()
