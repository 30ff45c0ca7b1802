"""What peg removal's reset agent does from the states where its resets began: the run's reset actor frozen at one
checkpoint, restarted from each logged trigger state of a stretch of the run, for a whole reset episode.

    python results/table1-four-tasks/probes/peg_remove_resets.py runs/every-task/peg_insertion_remove/ours/seed0 \\
        --checkpoint checkpoints/kept/step_0000100000 --frames 90000:100000

Peg removal observes the arm's 7 joint positions and velocities, and the peg is rigidly held, so each row of
``triggers.csv`` (the observation before a triggered reset) is the whole physical state: the probe places the env
there (``set_state``) and steps the reset actor for the reset horizon, as a reset episode would (success: in the
hole after at least ``reset.min_steps`` steps). Three actors from the same states: the reset actor sampled as in
training, the same greedy, and zero torque (the arm left to its damping). For each: the success share with a 95%
Wilson interval, the peg's distance to its goal pose (``d_goal``, metres over both ends; in the hole below 0.1)
at the start, at its closest and at the end (medians), the share of steps with the peg's bottom below the table
top, and the mean absolute action with the share of saturated action components (|a| > 0.99). No update is made.
"""
from __future__ import annotations

import argparse
import csv
import statistics
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_reset_envs import PegInsertionEnv
from torchrl_reset_recipes.analysis.runs import wilson_interval
from torchrl_reset_recipes.analysis.saved_runs import load_agents
from torchrl_reset_recipes.training.agents import with_exploration
from torchrl_reset_recipes.training.task_envs import make_task_env

TABLE_TOP = -0.4


def trigger_states(run_dir: Path, low: int, high: int) -> list[np.ndarray]:
    with open(run_dir / "triggers.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if low <= int(r["frames"]) < high]
    return [np.array(r["observation"].split(), dtype=np.float64) for r in rows]


def episode(env: PegInsertionEnv, state: np.ndarray, act, horizon: int, min_steps: int) -> dict:
    env.reset()
    env.set_state(state[:7], state[7:])
    obs = env._observation().astype(np.float32)
    d = [env.d_goal()]
    below, actions, success = 0, [], False
    for step in range(1, horizon + 1):
        action = act(obs)
        obs, *_ = env.step(action)
        actions.append(np.abs(action))
        d.append(env.d_goal())
        below += float(env.data.site_xpos[env._bottom][2]) < TABLE_TOP
        if step >= min_steps and env.in_hole():
            success = True
            break
    a = np.stack(actions)
    return {"success": success, "d_start": d[0], "d_min": min(d), "d_end": d[-1], "below": below / len(actions),
            "mean_abs_action": float(a.mean()), "saturated": float((a > 0.99).mean()), "steps": len(actions)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--checkpoint", default=None)
    parser.add_argument("--frames", default="0:100000000", help="the stretch of trigger states, FROM:TO frames")
    parser.add_argument("--seed", type=int, default=1000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    low, high = (int(x) for x in args.frames.split(":"))
    saved = load_agents(args.run_dir, checkpoint=args.checkpoint)
    spec = saved.spec
    if spec.cfg.task.name != "peg_insertion_remove":
        raise SystemExit(f"{args.run_dir} is a {spec.cfg.task.name} run; this probe reads peg removal's states")
    states = trigger_states(args.run_dir, low, high)
    if not states:
        raise SystemExit(f"no trigger in frames {low}-{high} of {args.run_dir}/triggers.csv")
    torch_env, _ = make_task_env(spec, saved.reset)
    sampled = with_exploration(saved.reset.actor, torch_env.action_spec, spec, saved.reset.head)
    env = PegInsertionEnv("remove")
    env.reset(seed=args.seed)
    if (env.model.nq, env.model.nv) != (7, 7):
        raise SystemExit("the peg model has more than the arm's 7 joints: an observation is not the whole state")

    def policy(actor, mode):
        def act(obs):
            with torch.no_grad(), set_exploration_type(mode):
                return actor(TensorDict(observation=torch.from_numpy(obs), batch_size=[]))["action"].numpy()
        return act

    actors = {"sampled": policy(sampled, ExplorationType.RANDOM),
              "greedy": policy(saved.reset.actor, ExplorationType.DETERMINISTIC),
              "zero torque": lambda obs: np.zeros(7, dtype=np.float32)}
    print(f"{args.run_dir} at step {saved.step}: {len(states)} trigger states of frames {low}-{high}, "
          f"{spec.reset_horizon} steps each, seed {args.seed}")
    print("reset actor | episodes | successful | share [95% interval] | d_goal start / closest / end (median) | "
          "steps below the table top | mean |a| | saturated")
    for name, act in actors.items():
        runs = [episode(env, s, act, spec.reset_horizon, int(spec.cfg.reset.min_steps)) for s in states]
        wins = sum(r["success"] for r in runs)
        lo, hi = wilson_interval(wins, len(runs))
        med = {k: statistics.median(r[k] for r in runs) for k in ("d_start", "d_min", "d_end")}
        print(f"{name} | {len(runs)} | {wins} | {wins / len(runs):.2f} [{lo:.2f}, {hi:.2f}] | "
              f"{med['d_start']:.3f} / {med['d_min']:.3f} / {med['d_end']:.3f} | "
              f"{statistics.mean(r['below'] for r in runs):.2f} | {statistics.mean(r['mean_abs_action'] for r in runs):.2f} | "
              f"{statistics.mean(r['saturated'] for r in runs):.2f}", flush=True)


if __name__ == "__main__":
    main()
