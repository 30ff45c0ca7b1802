"""Frozen: its question is decided. It last ran at commit 271779f, as results/100000-tanh-normal-auto/probes/trigger_actions.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/100000-tanh-normal-auto/probes/trigger_actions.py --help``.

What the trigger scores at the states where it fired: the reset classifiers' p on the forward agent's action
against the reset actor's own, and how far out in the action box each agent's actions lie.

    python results/reset-actor-paper-sizes/probes/trigger_actions.py runs/100k-tanh_normal_auto/peg_insertion_insert/ours/seed0 \\
        --last 200

The trigger scores ``p(s, a)``, the reset classifiers' mean ratio, on the action ``a`` the forward agent is
about to execute (with its exploration noise) and fires below ``p_thresh``. The classifiers learn from the
reset agent's own transitions: where the forward agent's actions lie outside what the reset actor does, the
score of a forward action is an extrapolation. On the last ``--last`` trigger states before the checkpoint
(default: the run's latest), with both agents as the checkpoint holds them, no exploration, this prints the
share of states below ``p_thresh`` and the median p for: the forward actor's action, the reset actor's, the
zero action, and the forward actor's action halved; then, over all rows of both replay buffers, the share of
action components beyond +-0.9 and +-0.99 (the forward rows hold the executed, noisy actions).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

from torchrl_reset_recipes.analysis.saved_runs import (greedy_actions, load_agents, load_replay, logged_observations,
                                                       run_table, trigger_probability)


def trigger_states(run: Path, upto: int, last: int) -> torch.Tensor:
    rows = [r for r in run_table(run, "triggers.csv") if int(r["frames"]) <= upto][-last:]
    if not rows:
        raise SystemExit(f"{run} logged no trigger by step {upto}")
    return logged_observations(rows)


def out_in_the_box(actions: torch.Tensor) -> str:
    return f"{float((actions.abs() > 0.9).float().mean()):.0%} beyond +-0.9, {float((actions.abs() > 0.99).float().mean()):.0%} beyond +-0.99"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a run folder of ours (runs/<task>/ours/seed<k>)")
    parser.add_argument("--checkpoint", default=None,
                        help="a checkpoint of the run (default: its latest), or a kept state (checkpoints/kept/step_<n>, "
                             "agents only: no replay rows to describe)")
    parser.add_argument("--last", type=int, default=200, help="how many of the last trigger states")
    args = parser.parse_args(argv)
    if args.last < 1:
        parser.error("--last must be at least 1")
    saved = load_agents(args.run, checkpoint=args.checkpoint)
    if saved.spec.kind.name != "ours":
        raise SystemExit(f"{args.run} is a run of {saved.spec.kind.name}: this probe reads ours' classifiers")
    p_thresh, model = saved.spec.trigger_threshold, saved.reset.model
    states = trigger_states(args.run, saved.step, args.last)
    forward_action, reset_action = greedy_actions(saved.forward.actor, states), greedy_actions(saved.reset.actor, states)
    print(f"{args.run} at {saved.checkpoint.name}: the last {len(states)} trigger states, p_thresh {p_thresh}")
    print("| action scored | median p | below p_thresh |")
    print("|---|---|---|")
    for name, action in (("forward actor's", forward_action), ("reset actor's", reset_action),
                         ("zero", torch.zeros_like(forward_action)), ("forward actor's, halved", forward_action / 2)):
        p = trigger_probability(model, states, action)
        print(f"| {name} | {float(p.median()):.3f} | {float((p < p_thresh).float().mean()):.0%} |")
    print(f"forward actor at these states: {out_in_the_box(forward_action)}")
    print(f"reset actor at these states: {out_in_the_box(reset_action)}")
    for agent in ("forward", "reset"):
        try:
            rb = load_replay(args.run, agent, checkpoint=saved.checkpoint)
        except FileNotFoundError as err:  # a kept state (agents only), or an agent that had stored no step yet
            print(f"{agent} replay: none here ({err})")
            continue
        rows = min(rb.write_count, rb.storage.max_size)
        print(f"{agent} replay, {rows} rows: {out_in_the_box(rb.storage[:rows]['action'])}")


if __name__ == "__main__":
    main()
