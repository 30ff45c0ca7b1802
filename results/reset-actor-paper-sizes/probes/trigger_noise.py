"""Frozen: its question is decided. It last ran at commit 271779f, as results/100000-tanh-normal-auto/probes/trigger_noise.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/100000-tanh-normal-auto/probes/trigger_noise.py --help``.

Does the forward agent's exploration noise, carried from one forward episode to the next, keep the trigger
firing at the start? Frozen agents, forward episodes only, the noise handled four ways.

    python results/reset-actor-paper-sizes/probes/trigger_noise.py runs/peg-early-triggers/learn_from_forward/peg_insertion_insert/ours/seed0 \\
        --checkpoint checkpoints/kept/step_0000045000 --episodes 100

The runs follow the release: the forward agent's Ornstein-Uhlenbeck noise is never restarted
(``exploration.restart: never``, ``docs/method.md`` section 9) and is not clipped to the action box
(``exploration.clip: false``): the trigger scores the action as drawn, beyond +-1 where the noise takes it, and the
env clamps it. The noise's correlation time is ``1 / (theta dt)`` = 133 of the forward agent's steps (its
stationary standard deviation ``sigma / sqrt(2 theta)`` = 0.37 per component), and the noise moves only when the
forward agent acts; in a stretch of short cycles (a forward episode of a step or two, stopped by the trigger, then
a reset episode) the same noise is therefore scored again cycle after cycle.

With both agents as a checkpoint (or a kept state) holds them, and nothing learning, this runs ``--episodes``
forward episodes of at most the task's H_f steps, each from a fresh start state of the task (``env.reset()``:
in the run a forward episode starts where a successful reset ended, inside the same at-initial-state check), and
before each action scores it as the trigger does (the classifiers' mean ratio ``p``; it fires below p_thresh and
the action is not executed). The forward action is the actor's, without noise, plus the runs' own noise module
(the recipe's ``with_exploration``, fed one action at a time as the collector feeds it) handled as:

- ``carried``: as in the runs: one noise process through all episodes, started at its stationary spread
  (``--burn-in`` steps from zero before the first episode), a step of it at every scored action;
- ``carried, clipped``: the same noise, the noisy action clipped to the box before it is scored and executed
  (``exploration.clip=true``);
- ``restarted``: the noise restarted at zero at every forward episode's start (``exploration.restart=episode``,
  the paper's Table 1);
- ``none``: no noise.

The four share one random stream and the same start states (the env and the noise seeded with ``--seed`` in
each). Per case: the share of episodes the trigger ended, the share ended before a third action, the median
number of actions executed before a trigger, the share of the triggers that fired at a state inside the task's
own at-initial-state check (``reset_success``), and the forward steps per episode.

``--trajectory N`` also prints the first N steps of one noise-free forward episode from the first start state,
the trigger switched off: at each state, whether it is inside the check, and the classifiers' p of the forward
actor's action, of the reset actor's (both without noise) and of the zero action: how fast the classifiers'
score falls as the forward agent moves off the start, whichever action is scored.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

from torchrl_reset_envs import make_env
from torchrl_reset_recipes.analysis.saved_runs import CarriedNoise, greedy_actions, load_agents, trigger_probability
from torchrl_reset_recipes.training.agents import with_exploration
from torchrl_reset_recipes.training.task_envs import env_kwargs

CASES = ("carried", "carried, clipped", "restarted", "none")


def run_case(case: str, saved, episodes: int, seed: int, burn_in: int) -> dict:
    cfg, spec = saved.cfg, saved.spec
    env = make_env(cfg.task.name, **env_kwargs(cfg, for_eval=True))
    env.set_seed(seed)
    torch.manual_seed(seed)  # the noise module draws from torch's global generator, as in the runs
    low, high = env.action_spec.space.low, env.action_spec.space.high
    noise = CarriedNoise(with_exploration(saved.forward.actor, env.action_spec, spec)[-1])
    for _ in range(burn_in):
        noise(torch.zeros(env.action_spec.shape))
    horizon, p_thresh = spec.forward_horizon, float(spec.trigger_threshold)
    executed, triggered, at_start = [], [], []
    for _ in range(episodes):
        td = env.reset()
        if case == "restarted":
            noise.restart()
        steps, fired = 0, False
        while steps < horizon:
            observation = td["observation"].reshape(1, -1)
            action = greedy_actions(saved.forward.actor, observation)[0]
            if case != "none":
                action = noise(action)
            if case == "carried, clipped":
                action = action.clamp(low, high)
            if float(trigger_probability(saved.reset.model, observation, action.reshape(1, -1))) < p_thresh:
                fired = True
                at_start.append(bool(td["reset_success"].any()))
                break
            td = env.step(td.set("action", action))["next"]
            steps += 1
            if bool(td["done"].any()):
                break
        executed.append(steps)
        triggered.append(fired)
    env.close()
    stopped = [s for s, f in zip(executed, triggered) if f]
    return {
        "episodes": episodes,
        "triggered": sum(triggered) / episodes,
        "within two actions": sum(s < 2 for s in stopped) / episodes,
        "median actions before a trigger": (float(torch.tensor(stopped, dtype=torch.float).median()) if stopped
                                            else float("nan")),
        "triggers at the start": sum(at_start) / len(at_start) if at_start else float("nan"),
        "forward steps per episode": sum(executed) / episodes,
    }


def trajectory(saved, steps: int, seed: int) -> None:
    """The classifiers' p along the first ``steps`` steps of a noise-free forward episode, the trigger off."""
    env = make_env(saved.cfg.task.name, **env_kwargs(saved.cfg, for_eval=True))
    env.set_seed(seed)
    td = env.reset()
    print(f"A noise-free forward episode, the trigger off (p_thresh {saved.spec.trigger_threshold}):")
    print("| step | inside the check | p, forward actor's action | p, reset actor's | p, zero action |")
    print("|---|---|---|---|---|")
    for step in range(steps):
        observation = td["observation"].reshape(1, -1)
        forward_action = greedy_actions(saved.forward.actor, observation)
        scores = [float(trigger_probability(saved.reset.model, observation, action)) for action in
                  (forward_action, greedy_actions(saved.reset.actor, observation), torch.zeros_like(forward_action))]
        inside = "yes" if bool(td["reset_success"].any()) else "no"
        print(f"| {step} | {inside} | " + " | ".join(f"{p:.3f}" for p in scores) + " |")
        td = env.step(td.set("action", forward_action[0]))["next"]
        if bool(td["done"].any()):
            break
    env.close()


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a run folder of ours")
    parser.add_argument("--checkpoint", default=None,
                        help="a checkpoint of the run (default: its latest), or a kept state (checkpoints/kept/step_<n>)")
    parser.add_argument("--episodes", type=int, default=100, help="forward episodes per case")
    parser.add_argument("--seed", type=int, default=0, help="seeds the env and the noise, the same in every case")
    parser.add_argument("--burn-in", type=int, default=1000,
                        help="steps of the carried noise from zero before the first episode")
    parser.add_argument("--trajectory", type=int, default=0,
                        help="print the classifiers' p along the first N steps of a noise-free forward episode")
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.burn_in < 0 or args.trajectory < 0:
        parser.error("--episodes must be at least 1, --burn-in and --trajectory at least 0")
    saved = load_agents(args.run, checkpoint=args.checkpoint)
    if saved.spec.kind.name != "ours":
        raise SystemExit(f"{args.run} is a run of {saved.spec.kind.name}: this probe reads ours' classifiers")
    print(f"{args.run} at {saved.checkpoint.name}: {args.episodes} forward episodes per case, "
          f"H_f {saved.cfg.task.forward_horizon}, p_thresh {saved.spec.trigger_threshold}, seed {args.seed}")
    if args.trajectory:
        trajectory(saved, args.trajectory, args.seed)
    rows = {case: run_case(case, saved, args.episodes, args.seed, args.burn_in) for case in CASES}
    keys = list(next(iter(rows.values())))[1:]
    print("| noise | " + " | ".join(keys) + " |")
    print("|---|" + "---|" * len(keys))
    for case, row in rows.items():
        cells = ["-" if row[k] != row[k] else  # no trigger: no median, no share of triggers
                 f"{row[k]:.0%}" if k in ("triggered", "within two actions", "triggers at the start") else f"{row[k]:.1f}"
                 for k in keys]
        print(f"| {case} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
