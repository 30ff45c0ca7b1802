"""Frozen: its question is decided. It last ran at commit 271779f, as results/lnt-sparse/probes/offline_options.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/lnt-sparse/probes/offline_options.py --help``.

LNT-sparse's Q-ensemble trained afresh on one run's rows under each of the authors' K-critic options.

    python results/lnt-sparse/probes/offline_options.py \
        runs/lnt-sparse/peg_insertion_insert/lnt_sparse/seed0/checkpoints/step_0000025000 \
        --seeds 0 1 --updates 1000 --out results/lnt-sparse/probes/offline_options.csv

Does the release's way of running K critics make LNT-sparse's ensemble minimum more pessimistic where the
forward agent goes, so that its trigger fires there (the paper's LNT-sparse needs a manual reset nearly every
forward episode; the project's resets)? Data: the run's replay buffers at its checkpoint (forward rows: what
the trigger scores; reset rows: what the reset agent trains on). For each ``--seeds`` and each option (the
project's LNT-sparse; each of ``algo.independent_batches``, ``algo.member_actor_gradient``,
``algo.target_draws``, ``algo.sampling=episode`` alone; all four, as ``algo=lnt_sparse_release``), a fresh
reset agent built by the recipe from the run's own config (``make_reset_agent``) takes ``--updates`` updates of the recipe's
(``train.update``), on batches drawn from the reset rows as the option's buffer would draw them (uniform over
rows, or an episode first and then a step in it; K batches with independent batches) and completed by the
kind's ``prepare`` (the sparse reward). Every ``--every`` updates: over every forward row (s, a), the ensemble
minimum (the trigger's score: mean, and the share below Q_thresh, where the trigger would fire) and the
members' spread; over the reset rows one step from success, the minimum (these should stay high).
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path

import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

from torchrl_reset_recipes.analysis.saved_runs import ensemble_minimum, load_replay, new_reset_agent, offline_updates, run_config
from torchrl_reset_recipes.training.run_spec import run_spec

#: each option alone, then all four (what ``algo=lnt_sparse_release`` turns on)
RELEASE = {"algo.independent_batches": True, "algo.member_actor_gradient": True, "algo.target_draws": True,
           "algo.sampling": "episode"}
PROJECT = {"algo.independent_batches": False, "algo.member_actor_gradient": False, "algo.target_draws": False,
           "algo.sampling": "transition"}
OPTIONS = {"project": PROJECT, **{key.split(".")[1]: {**PROJECT, key: value} for key, value in RELEASE.items()},
           "all_four": RELEASE}


def config(run: Path, seed: int, settings: dict):
    """The run's own config (its networks, K, batch size...) with ``settings`` and ``seed`` set."""
    cfg = run_config(run)
    cfg.seed = seed
    for key, value in settings.items():
        OmegaConf.update(cfg, key, value, force_add=True)
    return cfg


def run_rows(checkpoint: Path) -> tuple[TensorDict, TensorDict]:
    """The forward and reset rows of the run's replay buffers at ``checkpoint`` (in the order written)."""
    run = checkpoint.parents[1]
    rows = []
    for agent in ("forward", "reset"):
        rb = load_replay(run, agent, checkpoint=checkpoint)
        if rb.write_count > rb.storage.max_size:
            raise SystemExit(f"{checkpoint / f'{agent}_buffer'} was filled: its first rows were overwritten")
        rows.append(rb.storage[:rb.write_count].clone())
    return rows[0], rows[1]


def episode_of_rows(replay: TensorDict) -> torch.Tensor:
    """Each reset row's episode index, from the end flags (the rows are in the order they were written)."""
    done = replay["next", "done"].reshape(-1).long()
    return torch.cumsum(done, 0) - done  # a row's episode: the number of episodes that ended before it


def draw_rows(replay: TensorDict, episodes: torch.Tensor | None, count: int, generator) -> torch.Tensor:
    """``count`` row indices: uniform over rows, or (``episodes`` given) an episode first, then a step in it."""
    if episodes is None:
        return torch.randint(replay.shape[0], (count,), generator=generator)
    starts = torch.searchsorted(episodes, torch.arange(int(episodes[-1]) + 1))
    ends = torch.cat([starts[1:], torch.tensor([episodes.numel()])])
    chosen = torch.randint(starts.numel(), (count,), generator=generator)
    lengths = ends[chosen] - starts[chosen]
    return starts[chosen] + (torch.rand(count, generator=generator) * lengths).long()


def train_and_watch(run, forward, replay, option, settings, seed, updates, every) -> list[dict]:
    spec = run_spec(config(run, seed, settings), check=False)
    cfg = spec.cfg
    agent = new_reset_agent(spec, seed)
    q_thresh, members = spec.trigger_threshold, int(cfg.algo.num_members)
    rows = int(cfg.reset.batch_size) * (members if spec["algo.independent_batches"] else 1)
    episodes = episode_of_rows(replay) if spec["algo.sampling"] == "episode" else None
    near = replay[replay["next", "reset_success"].reshape(-1)]
    generator = torch.Generator().manual_seed(seed)
    out = []

    def watch(step):
        out.append({"option": option, "seed": seed, "updates": step,
                    **ensemble_minimum(agent.model, forward, near, q_thresh)})

    def next_batch():
        sample = replay[draw_rows(replay, episodes, rows, generator)].clone()
        return spec.kind.prepare(sample, {}, None, spec)  # the sparse reward; member k's batch at [k]

    offline_updates(agent, next_batch, updates, every, watch, release_order=spec["update_order"] == "release")
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path, help="an LNT-sparse run's checkpoint folder (run/checkpoints/step_*)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--options", nargs="+", default=list(OPTIONS), choices=list(OPTIONS), metavar="OPTION",
                        help=f"among: {', '.join(OPTIONS)}")
    parser.add_argument("--updates", type=int, default=1000)
    parser.add_argument("--every", type=int, default=250)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=None, help="CSV of every recorded row")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    forward, replay = run_rows(args.checkpoint)
    near = int(replay["next", "reset_success"].sum())
    print(f"{args.checkpoint}: {forward.shape[0]} forward rows, {replay.shape[0]} reset rows ({near} one step from "
          f"success)", flush=True)
    first = True
    for seed in args.seeds:
        for option in args.options:
            trace = train_and_watch(args.checkpoint.parents[1], forward, replay, option, OPTIONS[option], seed,
                                    args.updates, args.every)
            if args.out:  # each variant's rows as soon as they are in: a stopped probe keeps what it measured
                with open(args.out, "w" if first else "a", newline="") as f:
                    writer = csv.DictWriter(f, fieldnames=list(trace[0]))
                    if first:
                        writer.writeheader()
                    writer.writerows(trace)
                first = False
            for r in (trace[0], trace[-1]):
                print(f"seed {seed} {option:>21} at {r['updates']:>5} updates: forward rows' minimum "
                      f"{r['forward_min_mean']:.3f} ({r['forward_below_q_thresh']:.0%} below Q_thresh), member std "
                      f"{r['forward_member_std']:.3f}; near success {r['near_success_min_mean']:.3f} "
                      f"({r['near_success_below_q_thresh']:.0%} below)", flush=True)


if __name__ == "__main__":
    main()
