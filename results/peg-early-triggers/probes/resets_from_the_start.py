"""Frozen: its question is decided. It last ran at commit 271779f, as results/peg-early-triggers/probes/resets_from_the_start.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/peg-early-triggers/probes/resets_from_the_start.py --help``.

Reset episodes from the states where the trigger fired inside the at-initial-state check: how many the
minimum of 5 reset steps turns into failures.

    python results/peg-early-triggers/probes/resets_from_the_start.py runs/peg-early-triggers/learn_from_forward/peg_insertion_insert/ours/seed0 \\
        --checkpoint checkpoints/kept/step_0000045000 --start 40000 --end 50000

A reset episode ends in success when the state passes the task's check (``d_start < 0.2``) after at least
``reset.min_steps`` steps (5, the release's ``min_episode_steps``), so one that a trigger begins inside the check
can still leave it and fail. On peg insertion (insert), from the run's logged trigger states of the stretch
(``triggers.csv``: the arm's joint positions and velocities) that lie inside the check, with the reset actor as
the checkpoint (or kept state) holds it, nothing learning: each state is set in the task's model, the reset actor
acts from it as it explores in the run (a tanh-Gaussian samples; a deterministic actor acts without its noise)
for the run's reset horizon, and the episode would have succeeded with a minimum of 1 step if any state after it
passes the check, with a minimum of 5 if any state from the fifth step on does. Also: how many of the episodes
left the check within their first 5 steps.
"""
from __future__ import annotations

import argparse
import runpy
from pathlib import Path

import mujoco
import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_reset_envs import PegInsertionEnv
from torchrl_reset_recipes.analysis.saved_runs import load_agents, run_table

_measure = runpy.run_path(str(Path(__file__).with_name("measure.py")))  # the check, worked out as measure.py does
CHECK = _measure["CHECK"]


def reset_episode(env: PegInsertionEnv, actor, observation: np.ndarray, horizon: int) -> list[bool]:
    """Whether each state of a reset episode from ``observation`` (joint positions, then velocities) passes the check."""
    env.reset()  # the env's own episode bookkeeping; the state is then set
    env.data.qpos[env._qadr] = observation[:7]
    env.data.qvel[:] = 0.0
    env.data.qvel[env._vadr] = observation[7:14]
    mujoco.mj_forward(env.model, env.data)
    state, inside = torch.as_tensor(observation, dtype=torch.float32), []
    for _ in range(horizon):
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            action = actor(TensorDict(observation=state.reshape(1, -1), batch_size=[1]))["action"][0]
        state, _, _, _, info = env.step(action.numpy())
        state = torch.as_tensor(state, dtype=torch.float32)
        inside.append(bool(info["reset_success"]))
    return inside


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a run folder of ours on peg insertion (insert)")
    parser.add_argument("--checkpoint", default=None,
                        help="a checkpoint of the run (default: its latest), or a kept state (checkpoints/kept/step_<n>)")
    parser.add_argument("--start", type=int, default=40000)
    parser.add_argument("--end", type=int, default=50000)
    parser.add_argument("--last", type=int, default=60, help="at most this many of the stretch's last trigger states")
    parser.add_argument("--seed", type=int, default=0, help="seeds the reset actor's samples")
    args = parser.parse_args(argv)
    if not 0 <= args.start < args.end or args.last < 1:
        parser.error("the stretch needs 0 <= --start < --end, and --last at least 1")
    saved = load_agents(args.run, checkpoint=args.checkpoint, agents=("reset",))
    if saved.cfg.task.name != "peg_insertion_insert":
        raise SystemExit(f"{args.run} is a run of {saved.cfg.task.name}: the check here is peg insertion (insert)'s")
    horizon = saved.spec.reset_horizon  # H_r, as the recipe works it out
    min_steps = int(saved.cfg.reset.min_steps)
    env = PegInsertionEnv("insert")
    env.reset(seed=args.seed)
    torch.manual_seed(args.seed)
    rows = [r for r in run_table(args.run, "triggers.csv") if args.start < int(r["frames"]) <= args.end][-args.last:]
    states = [np.array(r["observation"].split(), dtype=float) for r in rows]
    states = [s for s in states if _measure["d_start"](env, s[:7]) < CHECK]
    print(f"{args.run} at {saved.checkpoint.name}: of the last {len(rows)} trigger states in {args.start}-{args.end}, "
          f"{len(states)} inside the check; reset horizon {horizon}, the run's minimum {min_steps} steps")
    if not states:
        return
    episodes = [reset_episode(env, saved.reset.actor, s, horizon) for s in states]
    n = len(episodes)
    print("| reset episodes | successful with a minimum of 1 step | with a minimum of 5 | left the check within 5 steps |")
    print("|---|---|---|---|")
    print(f"| {n} | {sum(any(e) for e in episodes)} ({sum(any(e) for e in episodes) / n:.0%}) | "
          f"{sum(any(e[4:]) for e in episodes)} ({sum(any(e[4:]) for e in episodes) / n:.0%}) | "
          f"{sum(not all(e[:5]) for e in episodes)} ({sum(not all(e[:5]) for e in episodes) / n:.0%}) |")


if __name__ == "__main__":
    main()
