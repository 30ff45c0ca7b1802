"""Frozen: its question is decided. It last ran at commit 271779f, as results/screening-reset-actor/probes/reset_exploration.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/screening-reset-actor/probes/reset_exploration.py --help``.

Why the project's reset actor makes the trigger fire early: how wide the reset agent explores, and what its
classifiers make of actions outside that band, for the release's actor and the project's, seed by seed.

    python results/reset-actor-screening/probes/reset_exploration.py \\
        release=runs/screening/release tanh_normal_auto=runs/screening/tanh_normal_auto \\
        --seeds 0-9 --checkpoint step_0000015000 --last 2000 --out results/reset-actor-screening/probes

The reset classifiers learn from the reset agent's transitions only (B_r); the trigger scores the forward
agent's actions with them. For each run folder ``<folder>/seed<k>`` and its checkpoint ``--checkpoint``, on
the last ``--last`` rows of the reset replay buffer (states ``s``, stored, executed actions ``a``) and the
last 200 states where the trigger fired, with both agents as the checkpoint holds them and no exploration:

- ``spread``: the mean over rows and action components of ``|a - mu_r(s)|``, how far the executed reset
  actions lie from the reset actor's own deterministic action (the release's: OU noise; the project's:
  the tanh-Gaussian's samples);
- ``p_stored``, ``p_mu_r``, ``p_uniform``: the median over rows of the classifiers' mean ratio ``p`` (the
  trigger's score) at the stored action, at ``mu_r(s)`` and at an action drawn uniformly from the box
  (one draw per row, fixed generator): how sharply the classifiers fall off away from what the reset
  agent does;
- ``below_uniform``: the share of those rows whose uniform action scores below ``p_thresh``;
- ``trigger_p_forward``, ``trigger_below_forward``: at the trigger states, the median ``p`` of the
  forward actor's deterministic action and the share below ``p_thresh``;
- from the run's own tables, for steps up to the checkpoint: ``triggers`` (triggered resets) and
  ``forward_before_trigger``, the median number of forward steps in a forward episode that a trigger ended.

Writes ``reset_exploration.csv`` (one row per run) and ``reset_exploration.md`` (per configuration the mean
and bootstrap 95% interval over seeds, as the screening's table) to ``--out``.
"""
from __future__ import annotations

import argparse
import csv
import statistics
from pathlib import Path

import torch

from torchrl_reset_recipes.analysis.saved_runs import (greedy_actions, load_agents, load_replay, logged_observations,
                                                       run_table, trigger_probability)
from torchrl_reset_recipes.analysis.screen import bootstrap_interval, seed_runs

COLUMNS = ("spread", "p_stored", "p_mu_r", "p_uniform", "below_uniform", "trigger_p_forward",
           "trigger_below_forward", "triggers", "forward_before_trigger")


def forward_lengths_before_triggers(run: Path, upto: int) -> list[int]:
    """The forward steps of each forward episode that a trigger ended, up to step ``upto``: a reset episode
    logged at step ``frames`` after ``steps`` reset steps began at ``frames - steps``; the forward episode
    before it began where the previous reset episode ended."""
    lengths, previous = [], 0
    triggered = {int(r["frames"]) for r in run_table(run, "triggers.csv")}
    for row in run_table(run, "resets.csv"):
        end = int(row["frames"])
        if end > upto:
            break
        start = end - int(row["steps"])
        if start in triggered:  # a trigger is logged at the step count where it stopped the forward episode
            lengths.append(start - previous)
        previous = end
    return lengths


def probe_run(run: Path, checkpoint: str, last: int) -> dict[str, float]:
    saved = load_agents(run, checkpoint=run / "checkpoints" / checkpoint)
    if saved.spec.kind.name != "ours":
        raise SystemExit(f"{run} is a run of {saved.spec.kind.name}: this probe reads ours' classifiers")
    p_thresh, model = saved.spec.trigger_threshold, saved.reset.model
    rb = load_replay(run, "reset", checkpoint=saved.checkpoint)
    rows = min(rb.write_count, rb.storage.max_size)
    recent = rb.storage[max(0, rows - last):rows]
    states, stored = recent["observation"], recent["action"]
    mu_r = greedy_actions(saved.reset.actor, states)
    uniform = torch.rand(stored.shape, generator=torch.Generator().manual_seed(0)) * 2 - 1
    p_uniform = trigger_probability(model, states, uniform)
    trigger_rows = [r for r in run_table(run, "triggers.csv") if int(r["frames"]) <= saved.step][-200:]
    out = {"spread": float((stored - mu_r).abs().mean()),
           "p_stored": float(trigger_probability(model, states, stored).median()),
           "p_mu_r": float(trigger_probability(model, states, mu_r).median()),
           "p_uniform": float(p_uniform.median()),
           "below_uniform": float((p_uniform < p_thresh).float().mean())}
    if trigger_rows:
        trigger_states = logged_observations(trigger_rows)
        p_forward = trigger_probability(model, trigger_states, greedy_actions(saved.forward.actor, trigger_states))
        out["trigger_p_forward"] = float(p_forward.median())
        out["trigger_below_forward"] = float((p_forward < p_thresh).float().mean())
    else:
        out["trigger_p_forward"] = out["trigger_below_forward"] = float("nan")
    lengths = forward_lengths_before_triggers(run, saved.step)
    out["triggers"] = float(len(lengths))
    out["forward_before_trigger"] = float(statistics.median(lengths)) if lengths else float("nan")
    return out


def markdown(rows: list[dict]) -> str:
    names = list(dict.fromkeys(r["configuration"] for r in rows))
    lines = ["| configuration | seeds | " + " | ".join(COLUMNS) + " |", "|---|---|" + "---|" * len(COLUMNS)]
    for name in names:
        mine = [r for r in rows if r["configuration"] == name]
        cells = []
        for column in COLUMNS:
            mean, low, high = bootstrap_interval([r[column] for r in mine])
            cells.append(f"{mean:.3g}" + ("" if low != low else f" [{low:.3g}, {high:.3g}]"))
        lines.append(f"| {name} | {len(mine)} | " + " | ".join(cells) + " |")
    lines += ["", "Mean [bootstrap 95% interval] over the seeds (BCa, 10,000 resamples)."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("configurations", nargs="+", help="NAME=FOLDER, FOLDER holding seed<k>/ run folders")
    parser.add_argument("--seeds", default="0-9")
    parser.add_argument("--checkpoint", default="step_0000015000", help="the checkpoint of each run to read")
    parser.add_argument("--last", type=int, default=2000, help="how many of the newest reset replay rows")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    rows = []
    try:
        runs = seed_runs(args.configurations, args.seeds)
    except ValueError as err:
        parser.error(str(err))
    for name, seed, run in runs:
        row = {"configuration": name, "seed": seed, **probe_run(run, args.checkpoint, args.last)}
        print(", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()),
              flush=True)
        rows.append(row)
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "reset_exploration.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["configuration", "seed", *COLUMNS])
        writer.writeheader()
        writer.writerows(rows)
    read = (f"`{' '.join(args.configurations)}`, seeds {args.seeds}, checkpoint {args.checkpoint}, the last "
            f"{args.last} reset replay rows")
    (args.out / "reset_exploration.md").write_text(f"{read}\n\n" + markdown(rows))
    print(markdown(rows))


if __name__ == "__main__":
    main()
