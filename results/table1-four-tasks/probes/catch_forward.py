"""Why catch's forward return is 0 at 100k: how often its forward agent met the reward, how high it swung the ball,
and where the trigger stopped it.

    python results/table1-four-tasks/probes/catch_forward.py runs/every-task/ball_in_cup_catch/ours/seed0 \\
        --checkpoint checkpoints/step_0000100000

From the checkpoint's forward replay (every forward step of the run until the buffer is full): the rows whose
reward was 1 (the ball in the cup), then the ball's height above the string's anchor in the cup (metres; about
-0.3 hanging still, above 0 only on a swing over the rim) over ``--sample`` rows drawn at random (seed 0), each
row's state placed in the env; and the same height at every trigger state of ``triggers.csv``. A trigger firing at
high swings would stop the catches; one firing with the ball hanging does not. No update is made.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from torchrl_reset_envs import BallInCupEnv
from torchrl_reset_recipes.analysis.saved_runs import load_replay, logged_observations, run_config, run_table


def heights(env: BallInCupEnv, observation: torch.Tensor) -> np.ndarray:
    out = np.empty(len(observation))
    for i, row in enumerate(observation.double().numpy()):
        env.set_state(row[:4], row[4:])
        out[i] = float(env.ball_position()[1]) - float(env.data.site_xpos[env._cup_site][2])
    return out


def quantiles(values: np.ndarray, qs) -> str:
    return ", ".join(f"{q:g}: {v:+.3f}" for q, v in zip(qs, np.quantile(values, qs)))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--checkpoint", default=None, help="a checkpoint with its buffers (default: the latest)")
    parser.add_argument("--sample", type=int, default=5000, help="forward rows whose height is measured")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    if run_config(args.run_dir).task.name != "ball_in_cup_catch":
        raise SystemExit(f"{args.run_dir} is not a ball_in_cup_catch run")
    replay = load_replay(args.run_dir, "forward", checkpoint=args.checkpoint)
    n = min(replay.write_count, replay.storage.max_size)
    rows = replay.storage[:n]
    rewarded = int((rows["next", "reward"] > 0).sum())
    env = BallInCupEnv("catch")
    env.reset(seed=0)
    pick = torch.randperm(n, generator=torch.Generator().manual_seed(0))[:args.sample]
    forward = heights(env, rows["observation"][pick].float())
    triggers = logged_observations(run_table(args.run_dir, "triggers.csv"))
    at_triggers = heights(env, triggers)
    print(f"{args.run_dir}: {n} forward steps in the replay, {rewarded} with the ball in the cup (reward 1)")
    print(f"ball height above the anchor, {len(pick)} forward rows: quantiles {quantiles(forward, (0.5, 0.9, 0.99, 1))}; "
          f"above the anchor on {(forward > 0).mean():.1%}")
    print(f"the same at the {len(triggers)} trigger states: quantiles {quantiles(at_triggers, (0.1, 0.5, 0.9, 1))}; "
          f"above the anchor on {(at_triggers > 0).mean():.1%}")


if __name__ == "__main__":
    main()
