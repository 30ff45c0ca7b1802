"""Frozen: its question is decided. It last ran at commit 271779f, as results/100000-tier2/probes/reset_failures.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/100000-tier2/probes/reset_failures.py --help``.

Why do cliff-cheetah's reset episodes fail near the start? Replays a run's trigger states with its reset agent.

    python results/table1-cliff-cheetah/probes/reset_failures.py runs/tier2/cliff_cheetah/ours/seed1 --states 120

A run's ``resets.csv`` says which reset episodes failed (ran out of steps: a manual reset) but not how
they ended. This probe loads the run's latest checkpoint (its reset actor), takes the ``--states``
latest trigger states logged before that checkpoint (``triggers.csv`` keeps qpos and qvel), places
the task's own env in each, and runs the reset actor as training does (minimum reset steps, the
at-initial-state check ``|x| < 0.1`` and ``|pitch| < 0.1``, up to 2 H_f steps), once without exploration
and once with the run's Ornstein-Uhlenbeck noise (the noise starts at 0 here; in training it carries
over). Each episode that ends without success is classed by its last state: **flipped** (|pitch| > pi/2:
on its back, where a half-cheetah's torques cannot right it), **away** (upright but |x| >= 0.5) or
**near** (upright within 0.5 m of the start, not still enough or not level enough for the check);
with the sign of the end pitch (positive: nose down, the head below the torso).
Also printed: the logged outcome of the very reset that followed each trigger (paired by its start),
so that the replay can be compared with what happened in training (the policy has changed since),
and the reset actor's output on the chosen states before its tanh (a saturated tanh passes no gradient).
Last, what the check asks physically: from the task's start state, the actor's most common corner of the
action box held for 10 s against no torque, and how many steps of each pass the check.
"""
from __future__ import annotations

import argparse
import math
import statistics
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_reset_envs import make_gym_env

ROOT = Path(__file__).resolve().parents[3]

from torchrl_reset_recipes.training.run_spec import reset_horizon
from torchrl_reset_recipes.analysis.saved_runs import load_agents, logged_observations, run_config, run_table
from torchrl_reset_recipes.analysis.stretches import resets_by_start


def wrapped(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def ending(qpos: np.ndarray) -> str:
    if abs(wrapped(float(qpos[2]))) > math.pi / 2:
        return "flipped"
    return "away" if abs(float(qpos[0])) >= 0.5 else "near"


def replay(env, actor, qpos, qvel, *, horizon: int, min_steps: int, noise: dict | None, rng) -> dict:
    env.reset(seed=0)
    env.set_state(qpos, qvel)
    obs = np.concatenate([qpos, qvel]).astype(np.float32)
    ou = np.zeros(env.action_space.shape)
    for step in range(1, horizon + 1):
        with torch.no_grad():
            action = actor(TensorDict(observation=torch.as_tensor(obs)))["action"].numpy().astype(np.float64)
        if noise is not None:
            ou += noise["theta"] * -ou * noise["dt"] + noise["sigma"] * math.sqrt(noise["dt"]) * rng.standard_normal(ou.shape)
            action = np.clip(action + ou, -1.0, 1.0)
        obs, _, _, _, info = env.step(action)
        if bool(info["reset_success"]) and step >= min_steps:
            return {"outcome": "success", "steps": step}
    qpos_end = np.array(env.data.qpos)
    return {"outcome": ending(qpos_end), "steps": horizon, "x": float(qpos_end[0]), "pitch": wrapped(float(qpos_end[2]))}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a cliff-cheetah run folder written by recipes/train.py")
    parser.add_argument("--states", type=int, default=120, help="the latest trigger states to replay from")
    parser.add_argument("--seed", type=int, default=0, help="the exploration noise's and the env's seed")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="a checkpoint folder of the run (default: its latest); trigger states up to its step")
    args = parser.parse_args(argv)
    if args.states < 1:
        parser.error("--states must be positive")
    task = run_config(args.run).task.name
    if task != "cliff_cheetah":
        raise SystemExit(f"{args.run} is a {task} run; this probe reads cliff-cheetah states")
    saved = load_agents(args.run, checkpoint=args.checkpoint, agents=("reset",))
    cfg, latest, step = saved.cfg, saved.checkpoint, saved.step
    actor = saved.reset.actor.eval()
    triggers = [t for t in run_table(args.run, "triggers.csv") if int(t["frames"]) <= step]
    logged = {start: r["outcome"] for start, r in resets_by_start(args.run).items()}
    chosen = triggers[-args.states:]
    if not chosen:
        raise SystemExit(f"{args.run} logged no trigger up to its checkpoint {latest.name}: no trigger state to replay")
    env = make_gym_env("cliff_cheetah")
    nq = env.model.nq
    noise = {k: float(cfg.exploration[k]) for k in ("theta", "sigma", "dt")}
    rng = np.random.default_rng(args.seed)
    print(f"{args.run}: checkpoint {latest.name}; {len(chosen)} trigger states from frames "
          f"{chosen[0]['frames']} to {chosen[-1]['frames']}; reset horizon {reset_horizon(cfg)}, "
          f"minimum {int(cfg.reset.min_steps)} steps")
    states = logged_observations(chosen)
    with torch.no_grad():
        out = actor(TensorDict(observation=states, batch_size=[len(states)]))
    pre, act = out["action_preactivation"], out["action"]
    print("reset actor on these states: |pre-tanh output| median per motor "
          + " ".join(f"{v:.1f}" for v in pre.abs().median(0).values.tolist())
          + f"; action components at |a| > 0.99: {float((act.abs() > 0.99).float().mean()):.0%}; distinct sign patterns: "
          + str(len({tuple(row) for row in torch.sign(act).int().tolist()})))
    rows = []
    for t in chosen:
        o = np.array([float(v) for v in t["observation"].split()])
        row = {"frames": int(t["frames"]), "logged": logged.get(int(t["frames"]), "?"),
               "start_pitch": float(o[2]), "start_pitch_rate": float(o[nq + 2])}
        for name, n in (("greedy", None), ("noisy", noise)):
            r = replay(env, actor, o[:nq], o[nq:], horizon=reset_horizon(cfg), min_steps=int(cfg.reset.min_steps),
                       noise=n, rng=rng)
            row.update({f"{name}_{k}": v for k, v in r.items()})
        rows.append(row)
    # what the check asks, physically: from the task's start state, hold the actor's most common corner (its
    # signs) or no torque for 200 steps (10 s), and count the steps that pass the at-initial-state check
    signs = torch.sign(act).int().tolist()
    corner = max(set(map(tuple, signs)), key=signs.count)
    for label, held in (("the actor's most common corner " + str(corner), np.array(corner, dtype=np.float64)),
                        ("no torque", np.zeros(env.action_space.shape))):
        env.reset(seed=args.seed)
        passed = 0
        for _ in range(200):
            _, _, _, _, info = env.step(held)
            passed += bool(info["reset_success"])
        print(f"held from the start state for 200 steps, {label}: {passed} steps pass the check; last x "
              f"{float(env.data.qpos[0]):.2f}, pitch {wrapped(float(env.data.qpos[2])):.2f}")
    env.close()
    for name in ("greedy", "noisy"):
        counts = {k: sum(r[f"{name}_outcome"] == k for r in rows) for k in ("success", "flipped", "away", "near")}
        ok = [r[f"{name}_steps"] for r in rows if r[f"{name}_outcome"] == "success"]
        print(f"{name:6s}: " + ", ".join(f"{k} {v}" for k, v in counts.items())
              + (f"; median steps to success {statistics.median(ok):g}" if ok else ""))
        for outcome in ("flipped", "away", "near"):
            ended = [r for r in rows if r[f"{name}_outcome"] == outcome]
            if ended:
                print(f"        {outcome}: end x median {statistics.median(r[f'{name}_x'] for r in ended):.2f}, "
                      f"end |pitch| median {statistics.median(abs(r[f'{name}_pitch']) for r in ended):.2f}, "
                      f"nose down (pitch > 0) {sum(r[f'{name}_pitch'] > 0 for r in ended)} of {len(ended)}")
    print("logged outcome of the reset that followed these triggers in training: "
          + ", ".join(f"{k} {sum(r['logged'] == k for r in rows)}" for k in ("success", "manual", "?")))
    for kind in ("success", "manual"):
        sel = [r for r in rows if r["logged"] == kind]
        if sel:
            print(f"  logged {kind}: trigger-state |pitch| median {statistics.median(abs(r['start_pitch']) for r in sel):.3f}, "
                  f"pitch rate median {statistics.median(r['start_pitch_rate'] for r in sel):.2f}; replayed greedy: "
                  + ", ".join(f"{k} {sum(r['greedy_outcome'] == k for r in sel)}" for k in ("success", "flipped", "away", "near")))


if __name__ == "__main__":
    main()
