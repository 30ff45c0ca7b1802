"""Frozen: its question is decided. It last ran at commit 271779f, as results/lnt-sparse/probes/trained_ensembles.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/lnt-sparse/probes/trained_ensembles.py --help``.

LNT-sparse's trained Q-ensembles side by side: why the release's semantics keep the trigger firing.

    python results/lnt-sparse/probes/trained_ensembles.py \\
        project_seed0=runs/lnt-sparse/peg_insertion_insert/lnt_sparse/seed0:step_0000025000 \\
        release_seed0=runs/lnt-sparse/peg_insertion_insert/lnt_sparse_release/seed0:step_0000025000 \\
        release_seed1=runs/lnt-sparse/peg_insertion_insert/lnt_sparse_release/seed1:step_0000025000 \\
        --triggers 20 --rollouts 50 --out results/lnt-sparse/probes/trained_ensembles_25k.csv

Each ``NAME=RUN:CHECKPOINT`` names a run folder and one of its checkpoints (a folder name under the run's
``checkpoints/``, or a path). The probe loads each run's reset agent as that checkpoint holds it (the
recipe's own networks, from the run's config) and each run's forward rows (the forward replay buffer at that
checkpoint: the states and noisy actions the trigger scored). Every ensemble then scores every run's forward
rows, so that what the ensemble learned is told apart from where its forward agent went: per (ensemble,
rows), the trigger's score (the members' minimum: its mean and the share below Q_thresh, where the trigger
fires; and the share of the forward episodes, by the collector's ``traj_ids``, with a row below it: episodes
the trigger would stop now), the members' mean, their spread (standard deviation across members, averaged over rows) and the
gap between the mean and the minimum (how much the minimum's pessimism adds). Also, on each run's own reset
rows one step from success, the minimum (a reset agent that has learned its goal scores these high).

The forward rows are the steps the forward agent took: a step the trigger stopped is not taken and not stored,
so they leave out the states where the trigger fired. ``--triggers N`` adds those: each run's last N trigger
states logged up to its checkpoint (``triggers.csv``), with the action its forward actor takes there at the
checkpoint, without the exploration noise the trigger scored at the time.

The reset agent does not update during a forward episode (only the agent of the phase under way does), so the
trigger reads one ensemble through each forward episode: a checkpoint's ensemble is what the next forward
episodes meet. ``--rollouts E`` plays them: for every pair (one run's forward agent, one run's ensemble), E
forward episodes of H_f steps from the task's start, the forward actor's action plus the runs' own noise
(``with_exploration``'s Ornstein-Uhlenbeck module, carried from episode to episode as in the runs, after
``--burn-in`` steps from zero; the noisy action scored as drawn), the trigger armed with that ensemble and
Q_thresh: the share of episodes it stops and the median of the steps taken before it does. Every pair runs on
the same random draws (``--seed``: the env and the noise), so a difference between two pairs is theirs alone:
the rows of one forward agent tell its ensembles apart, the columns of one ensemble its forward agents.
"""
from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

import torch
from tensordict import TensorDict

from torchrl_reset_envs import make_env
from torchrl_reset_recipes.analysis.saved_runs import (CarriedNoise, ensemble_scores, greedy_actions, load_agents,
                                                       load_replay, logged_observations, model_values, run_table)
from torchrl_reset_recipes.training.agents import with_exploration
from torchrl_reset_recipes.training.reset_agents import LNTKind
from torchrl_reset_recipes.training.task_envs import env_kwargs


def parse(spec: str) -> tuple[str, Path, Path]:
    """``NAME=RUN:CHECKPOINT`` -> (name, run folder, checkpoint folder)."""
    name, sep, rest = spec.partition("=")
    run, sep2, checkpoint = rest.rpartition(":")
    if not sep or not sep2 or not name or not run or not checkpoint:
        raise SystemExit(f"name each ensemble as NAME=RUN:CHECKPOINT, got {spec!r}")
    run, checkpoint = Path(run), Path(checkpoint)
    if not checkpoint.exists() and (run / "checkpoints" / checkpoint).exists():
        checkpoint = run / "checkpoints" / checkpoint  # a checkpoint's name under the run's checkpoints/
    return name, run, checkpoint


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval (95% by default) of a share of ``k`` in ``n``."""
    share = k / n
    centre = (share + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(share * (1 - share) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def rollouts(saved, model, q_thresh: float, episodes: int, seed: int, burn_in: int) -> dict[str, float]:
    """``episodes`` forward episodes of ``saved``'s forward agent with the trigger armed with ``model`` (its members'
    minimum against ``q_thresh``), from the task's start, the runs' noise carried through them."""
    env = make_env(saved.cfg.task.name, **env_kwargs(saved.cfg, for_eval=True))
    env.set_seed(seed)
    torch.manual_seed(seed)  # the noise module draws from torch's global generator, as in the runs
    noise = CarriedNoise(with_exploration(saved.forward.actor, env.action_spec, saved.spec)[-1])
    for _ in range(burn_in):
        noise(torch.zeros(env.action_spec.shape))
    stopped = []  # per triggered episode, the steps taken before the trigger
    for _ in range(episodes):
        td = env.reset()
        for step in range(saved.spec.forward_horizon):
            observation = td["observation"].reshape(1, -1)
            action = noise(greedy_actions(saved.forward.actor, observation)[0])
            if float(model_values(model, observation, action.reshape(1, -1)).min()) < q_thresh:
                stopped.append(step)
                break
            td = env.step(td.set("action", action))["next"]
            if bool(td["done"].any()):
                break
    env.close()
    low, high = wilson(len(stopped), episodes)
    return {"episodes": episodes, "triggered": len(stopped) / episodes, "triggered_low": low, "triggered_high": high,
            "median_steps_before": float(torch.tensor(stopped, dtype=torch.float).median()) if stopped else float("nan")}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("ensembles", nargs="+", help="NAME=RUN:CHECKPOINT, one for each run to compare")
    parser.add_argument("--triggers", type=int, default=0,
                        help="also score each run's last N trigger states logged up to its checkpoint (triggers.csv) "
                             "with its forward actor's own action there, without noise")
    parser.add_argument("--rollouts", type=int, default=0,
                        help="also E forward episodes for every pair (forward agent, ensemble), the trigger armed")
    parser.add_argument("--seed", type=int, default=0, help="the rollouts' env and noise (the same for every pair)")
    parser.add_argument("--burn-in", type=int, default=1000, help="the rollouts' noise: steps from zero before them")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=None, help="CSV of every (ensemble, rows) pair")
    args = parser.parse_args(argv)
    if min(args.triggers, args.rollouts, args.burn_in) < 0:
        parser.error("--triggers, --rollouts and --burn-in must be at least 0")
    torch.set_num_threads(args.threads)
    runs = [parse(spec) for spec in args.ensembles]
    if len({name for name, _, _ in runs}) != len(runs):
        raise SystemExit("give each ensemble its own NAME")
    models, forward, near, thresholds, triggered, agents = {}, {}, {}, {}, {}, {}
    for name, run, checkpoint in runs:
        both = args.triggers or args.rollouts
        saved = load_agents(run, checkpoint=checkpoint, agents=("forward", "reset") if both else ("reset",))
        if not isinstance(saved.spec.kind, LNTKind):
            raise SystemExit(f"{run} is a run of {saved.spec.kind.name}: this probe reads LNT's Q-ensembles")
        models[name], thresholds[name], agents[name] = saved.reset.model, float(saved.spec.trigger_threshold), saved
        rows = []
        for agent in ("forward", "reset"):
            rb = load_replay(run, agent, checkpoint=saved.checkpoint)
            rows.append(rb.storage[:min(rb.write_count, rb.storage.max_size)].clone())
        forward[name] = rows[0]
        near[name] = rows[1][rows[1]["next", "reset_success"].reshape(-1)]
        print(f"{name}: {run} at {saved.step} steps, {rows[0].shape[0]} forward rows, {rows[1].shape[0]} reset rows "
              f"({near[name].shape[0]} one step from success), Q_thresh {thresholds[name]}", flush=True)
        if args.triggers:
            logged = [r for r in run_table(run, "triggers.csv") if int(r["frames"]) <= saved.step][-args.triggers:]
            if logged:
                states = logged_observations(logged)
                triggered[name] = TensorDict({"observation": states,
                                              "action": greedy_actions(saved.forward.actor, states)}, [len(states)])
                print(f"  its last {len(logged)} trigger states: logged at {logged[0]['frames']}-{logged[-1]['frames']} "
                      "steps", flush=True)
    tasks = {saved.cfg.task.name for saved in agents.values()}
    if len(tasks) != 1:
        raise SystemExit(f"the runs are of different tasks ({', '.join(sorted(tasks))}): compare runs of one task")
    if len(set(thresholds.values())) != 1:
        raise SystemExit(f"the runs' Q_thresh differ ({thresholds}): their triggers cannot be compared on one scale")
    q_thresh = next(iter(thresholds.values()))

    records = []
    for ensemble, model in models.items():
        for rows_of, rows in forward.items():
            episodes = rows["collector", "traj_ids"].reshape(-1)
            records.append({"ensemble": ensemble, "scored_on": f"{rows_of}'s forward rows",
                            **ensemble_scores(model, rows, q_thresh, episodes)})
        for rows_of, rows in triggered.items():
            records.append({"ensemble": ensemble, "scored_on": f"{rows_of}'s trigger states, its actor's action",
                            **ensemble_scores(model, rows, q_thresh)})
        records.append({"ensemble": ensemble, "scored_on": "its own rows one step from success",
                        **ensemble_scores(model, near[ensemble], q_thresh)})
    print("\n| ensemble | scored on | rows | minimum (the trigger's score) | below Q_thresh | episodes with one "
          "| members' mean | members' std | mean - minimum |\n|---|---|---|---|---|---|---|---|---|")
    for r in records:
        flagged = "" if r["episodes_flagged"] != r["episodes_flagged"] else f"{r['episodes_flagged']:.0%}"
        print(f"| {r['ensemble']} | {r['scored_on']} | {r['rows']} | {r['min_mean']:.3f} | {r['below_q_thresh']:.1%} | "
              f"{flagged} | {r['member_mean']:.3f} | {r['member_std']:.3f} | {r['mean_minus_min']:.3f} |")
    if args.rollouts:
        print(f"\nForward episodes with the trigger armed ({args.rollouts} per pair, H_f {saved.spec.forward_horizon}, "
              f"seed {args.seed}): the share the trigger stopped [Wilson 95% interval] (the median of the steps taken "
              "before it)")
        print("| forward agent | " + " | ".join(f"{name}'s ensemble" for name in models) + " |")
        print("|---|" + "---|" * len(models))
        for name, saved in agents.items():
            cells = []
            for ensemble, model in models.items():
                r = rollouts(saved, model, q_thresh, args.rollouts, args.seed, args.burn_in)
                records.append({"ensemble": ensemble, "scored_on": f"{name}'s forward agent, trigger armed", **r})
                median = "-" if r["median_steps_before"] != r["median_steps_before"] else f"{r['median_steps_before']:.0f}"
                cells.append(f"{r['triggered']:.0%} [{r['triggered_low']:.0%}, {r['triggered_high']:.0%}] ({median})")
            print(f"| {name}'s | " + " | ".join(cells) + " |", flush=True)
    if args.out:
        fields = list(dict.fromkeys(key for r in records for key in r))
        with open(args.out, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=fields)
            writer.writeheader()
            writer.writerows(records)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
