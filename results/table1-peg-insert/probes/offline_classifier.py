"""Frozen: its question is decided. It last ran at commit 271779f, as results/100000-release/probes/offline_classifier.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/100000-release/probes/offline_classifier.py --help``.

The reset classifier after a few hundred RCE updates on failed reset episodes, with both prior-bias draws.

    python results/table1-peg-insert/probes/offline_classifier.py --seeds 0 1 2 3 4 --updates 500 \
        --out results/table1-peg-insert/probes/offline_classifier.csv
    python results/table1-peg-insert/probes/offline_classifier.py --seeds 0 1 2 3 4 --targets copy  # targets copied

First, untrained agents (``--init-seeds`` per draw): the minimum-over-members label the members would
train on and the trigger's score, on 2000 rows of the failed reset episodes.

Peg-insertion (insert) at the recipe's paper settings. Data (once, seed 0): the untrained forward and
reset policies with their exploration noise act through forward episodes (H_f = 100) and reset
episodes (H_r = 200), the trigger switched off; the transitions of the reset episodes that failed
(ended by a manual reset) fill the reset replay buffer (the recipe's, with its n-step transform and
the release's episode-window sampler), and the start state is the only success example. Then, for
each seed and each draw of the priors' biases (``xavier``: the release's; ``fan_in``: this project's
earlier one), a fresh reset agent (the recipe's ``make_reset_agent``, at the recipe's settings: its
target classifiers start as in the release, unless ``--targets copy``) takes ``--updates`` updates with
the recipe's update (``train.update``: classifier step, then actor step with the updated classifiers,
then the soft target update). Every ``--every`` updates it records, on every replay row ``(s_t, a_t)``, the
trigger's score (the ensemble mean of ``p_i = exp(min(logit_i, 0))``) and the share of rows below
p_thresh, and the score at the start state with the forward actor's action there (what the trigger
sees at the start of a forward episode).
"""
import argparse
import csv
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[3]
from torchrl_reset_recipes.training.run_spec import run_spec
from torchrl_reset_recipes.training.buffers import make_buffers
from torchrl_reset_recipes.training.learner import make_collector
from torchrl_reset_recipes.training.agents import make_forward_agent, make_reset_agent
from torchrl_reset_recipes.training.task_envs import make_task_env, task_dimensions
from torchrl_reset_recipes.analysis.saved_runs import new_reset_agent, offline_updates

from torchrl_reset import DualCollector, success_probability  # noqa: E402


def config(overrides, settings=()):
    """The recipe's config for peg-insertion (insert) and ours, with ``settings`` (``--settings``), then the
    probe's own ``overrides``."""
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "conf"), version_base="1.3"):
        return compose("config", overrides=["task=peg_insertion_insert", "algo=ours", *settings, *overrides])


def failed_reset_episodes(min_rows: int, settings=()):
    """Reset transitions of failed reset episodes (manual resets), by untrained policies with noise."""
    cfg = config(["seed=0", "algo.threshold=1e-12"], settings)  # a threshold nothing falls below: no trigger
    torch.manual_seed(0)
    obs_dim, action_spec = task_dimensions(cfg)
    spec = run_spec(cfg, check=False)
    forward, reset = make_forward_agent(spec, obs_dim, action_spec), make_reset_agent(spec, obs_dim, action_spec)
    env, _ = make_task_env(spec, reset)
    collector = make_collector(spec, env, forward, reset)
    episodes, current, kept, outcomes = [], [], 0, {"success": 0, "manual": 0}
    for batch in collector:
        if DualCollector.phase_of(batch) == "reset":
            current.append(batch)
        for event in collector.pop_events():
            if event["phase"] != "reset":
                continue
            outcomes[event["outcome"]] = outcomes.get(event["outcome"], 0) + 1
            if event["outcome"] == "manual":
                episodes.append(torch.cat(current))
                kept += len(episodes[-1])
            current = []
        if kept >= min_rows:
            break
    start = collector.example_buffer
    collector.shutdown()
    return cfg, episodes, start, outcomes, forward


def at_initialisation(episodes, seeds, rows=2000, settings=()):
    """Untrained agents, each draw and seed: the minimum-over-members label (what every member trains on)
    and the trigger's score on ``rows`` replay rows of the failed reset episodes."""
    out = []
    for draw in ("fan_in", "xavier"):
        for seed in range(seeds):
            run_cfg = config([f"seed={seed}", f"algo.prior_bias_draw={draw}"], settings)
            spec = run_spec(run_cfg, check=False)
            agent = new_reset_agent(spec, seed)
            _, replay = make_buffers(spec)
            for episode in episodes:
                replay.extend(episode.select(*REPLAY_KEYS, strict=False))
            sample = replay.sample(rows)
            label, _ = agent.loss.labels(sample)
            with torch.no_grad():
                score = success_probability(agent.model.logits(sample["observation"], sample["action"])).mean(-1)
            out.append({"draw": draw, "seed": seed, "label_min_over_members": float(label.mean()),
                        "score_mean": float(score.mean()), "below_p_thresh": float((score < float(run_cfg.task.p_thresh)).float().mean())})
    return out


REPLAY_KEYS = ["observation", "action", ("next", "observation"), ("next", "done"), ("next", "truncated"),
               ("next", "terminated"), ("collector", "traj_ids")]


def train_and_watch(cfg, episodes, examples, forward_actor, seed, draw, updates, every, targets, settings=()):
    run_cfg = config([f"seed={seed}", f"algo.prior_bias_draw={draw}", f"target_init={targets}"], settings)
    spec = run_spec(run_cfg, check=False)
    agent = new_reset_agent(spec, seed)
    _, replay = make_buffers(spec)
    for episode in episodes:
        replay.extend(episode.select(*REPLAY_KEYS, strict=False))
    rows = torch.cat([e.select("observation", "action") for e in episodes])
    start = examples.sample(1)
    with torch.no_grad():
        start_action = forward_actor(start.select("observation").clone())["action"]
    p_thresh = float(run_cfg.task.p_thresh)
    model = agent.model
    out = []

    def watch(step):
        with torch.no_grad():
            score = success_probability(model.logits(rows["observation"], rows["action"])).mean(-1)
            at_start = success_probability(model.logits(start["observation"], start_action)).mean(-1)
        out.append({"seed": seed, "draw": draw, "targets": targets, "updates": step, "replay_score_mean": float(score.mean()),
                    "replay_below_p_thresh": float((score < p_thresh).float().mean()),
                    "start_score": float(at_start.reshape(-1)[0])})

    def next_batch():
        sample = replay.sample()
        sample.set("example", examples.sample(sample.shape[0]))
        return sample

    offline_updates(agent, next_batch, updates, every, watch, release_order=True)  # the recipe's update
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--updates", type=int, default=500)
    parser.add_argument("--every", type=int, default=25)
    parser.add_argument("--rows", type=int, default=4000, help="reset transitions of failed episodes to collect")
    parser.add_argument("--init-seeds", type=int, default=20, help="untrained agents measured per draw (0: none)")
    parser.add_argument("--targets", choices=["release", "copy"], default="release",
                        help="how the target classifiers start (the recipe's target_init)")
    parser.add_argument("--out", default=None, help="CSV of every recorded row")
    parser.add_argument("--settings", nargs="+", default=[], metavar="KEY=VALUE",
                        help="further config overrides (Hydra's syntax) for the data and every agent, e.g. "
                             "hidden_sizes=[16,16] task.forward_horizon=20 for a small try (default: none, the "
                             "recipe's paper settings); not the keys the probe sets itself (seed, "
                             "algo.prior_bias_draw, target_init, algo.threshold)")
    args = parser.parse_args()
    torch.set_num_threads(2)
    cfg, episodes, examples, outcomes, forward = failed_reset_episodes(args.rows, args.settings)
    print(f"data: {sum(len(e) for e in episodes)} transitions of {len(episodes)} failed reset episodes "
          f"(reset outcomes while collecting: {outcomes}); {len(examples)} success examples (the start state)")
    if args.init_seeds:
        init = at_initialisation(episodes, args.init_seeds, settings=args.settings)
        for draw in ("fan_in", "xavier"):
            mine = [r for r in init if r["draw"] == draw]
            mean = lambda key: sum(r[key] for r in mine) / len(mine)  # noqa: E731
            print(f"untrained, {draw:>6}, {len(mine)} seeds x 2000 rows: minimum-over-members label "
                  f"{mean('label_min_over_members'):.3f} (seeds {min(r['label_min_over_members'] for r in mine):.3f}-"
                  f"{max(r['label_min_over_members'] for r in mine):.3f}); trigger score {mean('score_mean'):.3f} "
                  f"(seeds {min(r['score_mean'] for r in mine):.3f}-{max(r['score_mean'] for r in mine):.3f}); "
                  f"rows below p_thresh {mean('below_p_thresh'):.1%}", flush=True)
        if args.out:
            with open(args.out.replace(".csv", "_init.csv"), "w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=list(init[0]))
                writer.writeheader()
                writer.writerows(init)
    rows = []
    for seed in args.seeds:
        for draw in ("fan_in", "xavier"):
            trace = train_and_watch(cfg, episodes, examples, forward.actor, seed, draw, args.updates, args.every,
                                    args.targets, args.settings)
            rows += trace
            below = [r["updates"] for r in trace if r["replay_score_mean"] < float(cfg.task.p_thresh)]
            print(f"seed {seed} {draw:>6}: replay score {trace[0]['replay_score_mean']:.3f} at 0 -> "
                  f"{trace[-1]['replay_score_mean']:.3f} at {trace[-1]['updates']} (min "
                  f"{min(r['replay_score_mean'] for r in trace):.3f}); mean below p_thresh from update "
                  f"{below[0] if below else 'never'}; rows below p_thresh at the end "
                  f"{trace[-1]['replay_below_p_thresh']:.0%}; start-state score {trace[0]['start_score']:.3f} -> "
                  f"{trace[-1]['start_score']:.3f}", flush=True)
    if args.out:
        with open(args.out, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


if __name__ == "__main__":
    main()
