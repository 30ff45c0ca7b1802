"""Frozen: its question is decided. It last ran at commit 271779f, as results/100000-release/probes/offline_lnt_ensemble.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/100000-release/probes/offline_lnt_ensemble.py --help``.

LNT-sparse's Q-ensemble trained afresh on a run's own data, without and with randomized priors.

    python results/table1-peg-insert/probes/offline_lnt_ensemble.py \
        runs/release/peg_insertion_insert/lnt_sparse/seed0/checkpoints/step_0000095000 \
        --upto 25000 --seeds 0 1 --updates 3000 --scales 0 3 --out results/table1-peg-insert/probes/offline_lnt_ensemble.csv

Why does LNT-sparse's trigger go quiet by 25k on peg-insertion (insert) while its reset agent cannot yet
reset from where the forward agent goes? Its 20 Q-functions (no priors, one mini-batch for all, targets
copied) end up nearly one function, and their minimum on the forward agent's states sits far above
Q_thresh = 0.1. Would members that disagree where there is no data (randomized priors, as ours' classifiers
have) keep it lower there?

Data: a run's replay buffers as its checkpoint holds them, cut to the rows the run had collected by
``--upto`` steps (``progress.csv``'s ``forward_steps`` and ``reset_steps`` at that row; the buffers are
written in order). For each ``--seeds`` and each ``--scales`` (``algo.prior_scale``: 0 is the paper
preset, 3 ours' beta with the release's prior draw), a fresh LNT-sparse reset agent (the recipe's
``make_reset_agent``) takes ``--updates`` updates of the recipe's (``train.update``, the release's order,
on batches of 256 of those reset rows, the kind's ``prepare`` writing the sparse reward). Every ``--every``
updates, over every forward row ``(s, a)`` (what the trigger scores), the ensemble minimum (mean, and the share
below Q_thresh) and the members' spread, and the minimum on the reset rows whose next state passes the
reset check (one step from success: those should stay high).
"""
import argparse
import csv
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict

ROOT = Path(__file__).resolve().parents[3]
from torchrl_reset_recipes.training.run_spec import run_spec
from torchrl_reset_recipes.analysis.saved_runs import ensemble_minimum, load_replay, new_reset_agent, offline_updates, run_table


def config(overrides):
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "conf"), version_base="1.3"):
        return compose("config", overrides=["task=peg_insertion_insert", "algo=lnt_sparse", *overrides])


def rows_at(checkpoint: Path, upto: int) -> tuple[TensorDict, TensorDict, int, int]:
    """The forward and reset replay rows the run had written by ``upto`` steps."""
    run = checkpoint.parents[1]
    row = next((r for r in run_table(run, "progress.csv") if int(r["frames"]) == upto), None)
    if row is None:
        raise SystemExit(f"{run}/progress.csv has no row at {upto} steps")
    forward_rows, reset_rows = int(row["forward_steps"]), int(row["reset_steps"])
    data = []
    for agent, count in (("forward", forward_rows), ("reset", reset_rows)):
        rb = load_replay(run, agent, checkpoint=checkpoint)
        if rb.write_count < count:
            raise SystemExit(f"{checkpoint / f'{agent}_buffer'} holds {rb.write_count} rows, fewer than the {count} "
                             f"written by {upto}")
        if rb.write_count > rb.storage.max_size:
            raise SystemExit(f"{checkpoint / f'{agent}_buffer'} was filled ({rb.write_count} rows written into "
                             f"{rb.storage.max_size}): its first rows are no longer those written first")
        data.append(rb.storage[:count].clone())
    return data[0], data[1], forward_rows, reset_rows


def train_and_watch(forward, replay, seed, scale, updates, every, batch_size=256):
    spec = run_spec(config([f"seed={seed}", f"algo.prior_scale={scale}"]), check=False)
    agent = new_reset_agent(spec, seed)
    q_thresh = spec.trigger_threshold  # LNT's Q_thresh (algo.threshold)
    near = replay[replay["next", "reset_success"].reshape(-1)]
    generator = torch.Generator().manual_seed(seed)
    out = []

    def watch(step):
        out.append({"seed": seed, "prior_scale": scale, "updates": step,
                    **ensemble_minimum(agent.model, forward, near, q_thresh)})

    def next_batch():
        sample = replay[torch.randint(replay.shape[0], (batch_size,), generator=generator)].clone()
        return spec.kind.prepare(sample, {}, None, spec)  # the sparse reward

    offline_updates(agent, next_batch, updates, every, watch, release_order=True)  # the recipe's update
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path, help="an LNT-sparse run's checkpoint folder (run/checkpoints/step_*)")
    parser.add_argument("--upto", type=int, default=25000, help="the rows the run had written by this step")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--scales", type=float, nargs="+", default=[0.0, 3.0], help="algo.prior_scale values")
    parser.add_argument("--updates", type=int, default=3000)
    parser.add_argument("--every", type=int, default=250)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=None, help="CSV of every recorded row")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    forward, replay, nf, nr = rows_at(args.checkpoint, args.upto)
    near = int(replay["next", "reset_success"].sum())
    print(f"data at {args.upto} steps: {nf} forward rows, {nr} reset rows ({near} one step from success)", flush=True)
    writer = None
    for seed in args.seeds:
        for scale in args.scales:
            trace = train_and_watch(forward, replay, seed, scale, args.updates, args.every)
            if args.out:  # each variant's rows as soon as they are in: a stopped probe keeps what it measured
                with open(args.out, "a" if writer else "w", newline="") as f:
                    writer = csv.DictWriter(f, fieldnames=list(trace[0]))
                    if f.tell() == 0:
                        writer.writeheader()
                    writer.writerows(trace)
            for r in (trace[0], trace[len(trace) // 2], trace[-1]):
                print(f"seed {seed} prior_scale {scale:g} at {r['updates']:>5} updates: forward rows' minimum "
                      f"{r['forward_min_mean']:.3f} ({r['forward_below_q_thresh']:.0%} below Q_thresh), member std "
                      f"{r['forward_member_std']:.3f}; near success {r['near_success_min_mean']:.3f} "
                      f"({r['near_success_below_q_thresh']:.0%} below)", flush=True)


if __name__ == "__main__":
    main()
