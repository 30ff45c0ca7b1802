"""Why ball-in-cup throw's resets fail in training but mostly succeed at the evaluations: the run's agents frozen at
one checkpoint, run by the recipe's own collector (its env, trigger, horizons and exploration) for a stretch of
steps, with and without each policy's exploration.

    python results/table1-four-tasks/probes/throw_resets.py runs/every-task/ball_in_cup_throw/ours/seed0 \\
        --checkpoint checkpoints/kept/step_0000100000 --steps 6000

For each variant (forward policy with its training noise or greedy, x reset policy sampled as in training or
greedy): the reset episodes, their success share with a 95% Wilson interval, and how the forward episodes ended
(triggered or requested) with their mean length. No update is made: the agents stay as saved.
"""
from __future__ import annotations

import argparse
from collections import Counter

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_reset import DualCollector
from torchrl_reset_recipes.analysis.runs import wilson_interval
from torchrl_reset_recipes.analysis.saved_runs import load_agents
from torchrl_reset_recipes.training.agents import with_exploration
from torchrl_reset_recipes.training.learner import event_keys, restart_option
from torchrl_reset_recipes.training.task_envs import make_task_env


def greedy(actor):
    def act(td):
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return actor(td)
    return act


def run(saved, *, noisy_forward: bool, sampled_reset: bool, steps: int, seed: int) -> dict:
    spec = saved.spec
    env, _ = make_task_env(spec, saved.reset)
    forward = with_exploration(saved.forward.actor, env.action_spec, spec) if noisy_forward else greedy(saved.forward.actor)
    reset = (with_exploration(saved.reset.actor, env.action_spec, spec, saved.reset.head) if sampled_reset
             else greedy(saved.reset.actor))
    collector = DualCollector(env, forward, reset, max_forward_steps=spec.forward_horizon,
                              max_reset_steps=spec.reset_horizon, min_reset_steps=int(spec.cfg.reset.min_steps),
                              total_frames=steps, event_keys=event_keys(env), **restart_option(spec))
    collector.set_seed(seed)
    for _ in collector:
        pass
    events = collector.pop_events()
    forward_ends = Counter(e["outcome"] for e in events if e["phase"] == "forward")
    forward_lengths = [e["steps"] for e in events if e["phase"] == "forward"]
    c = collector.counters
    low, high = wilson_interval(c["successful_resets"], c["reset_episodes"])
    collector.shutdown()
    return {"reset_episodes": c["reset_episodes"], "successful": c["successful_resets"],
            "share": c["successful_resets"] / max(c["reset_episodes"], 1), "interval": (low, high),
            "forward_ends": dict(forward_ends),
            "forward_length": sum(forward_lengths) / max(len(forward_lengths), 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir")
    parser.add_argument("--checkpoint", default=None)
    parser.add_argument("--steps", type=int, default=6000)
    parser.add_argument("--seed", type=int, default=1000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    saved = load_agents(args.run_dir, checkpoint=args.checkpoint)
    print(f"{args.run_dir} at step {saved.step}, {args.steps} steps per variant, seed {args.seed}")
    print("forward | reset | reset episodes | successful | share [95% interval] | forward ends | mean forward length")
    for noisy_forward in (True, False):
        for sampled_reset in (True, False):
            r = run(saved, noisy_forward=noisy_forward, sampled_reset=sampled_reset, steps=args.steps, seed=args.seed)
            print(f"{'noisy' if noisy_forward else 'greedy'} | {'sampled' if sampled_reset else 'greedy'} | "
                  f"{r['reset_episodes']} | {r['successful']} | {r['share']:.2f} [{r['interval'][0]:.2f}, "
                  f"{r['interval'][1]:.2f}] | {r['forward_ends']} | {r['forward_length']:.1f}", flush=True)


if __name__ == "__main__":
    main()
