"""Whether peg removal's reset classifiers point toward the hole: their success ratio ``p`` on the run's own reset
replay, grouped by how far each row's peg lies from its goal pose, beside their ``p`` on the initial-state examples.

    python results/table1-four-tasks/probes/peg_remove_classifier.py runs/every-task/peg_insertion_remove/ours/seed0 \\
        --checkpoint checkpoints/step_0000100000

Each reset replay row's observation is the whole physical state (the arm's 7 joint positions and velocities; the
peg is rigidly held), so the probe places the env there and reads ``d_goal`` (metres over both ends of the peg;
in the hole below 0.1 with its bottom under -0.45) and the peg bottom's height. The reset agent's model scores each
row twice, as ours' trigger reduces its members (the members' mean of ``C / (1 - C)``): on the action taken in the
row and on the reset actor's own greedy action. A classifier that guides the reset actor scores rows nearer the
goal higher. The examples are the states the run added to its example buffer (the start state after each manual
reset and the state each successful reset ended in): their number of distinct states, their ``d_goal`` and their
``p`` with the reset actor's action. Needs a checkpoint with its buffers (not a kept state). No update is made.
"""
from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import numpy as np
import torch

from torchrl_reset_envs import PegInsertionEnv
from torchrl_reset_recipes.analysis.saved_runs import (greedy_actions, load_agents, load_examples, load_replay,
                                                       trigger_probability)

BINS = (0.0, 0.1, 0.2, 0.3, 0.5, 0.8, float("inf"))


def peg_distances(env: PegInsertionEnv, observation: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """``d_goal`` and the peg bottom's height at each row's state."""
    d, z = np.empty(len(observation)), np.empty(len(observation))
    for i, row in enumerate(observation.double().numpy()):
        env.set_state(row[:7], row[7:])
        d[i], z[i] = env.d_goal(), float(env.data.site_xpos[env._bottom][2])
    return d, z


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--checkpoint", default=None, help="a checkpoint with its buffers (default: the latest)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    saved = load_agents(args.run_dir, checkpoint=args.checkpoint, agents=("reset",))
    if saved.spec.cfg.task.name != "peg_insertion_remove" or saved.spec.kind.name != "ours":
        raise SystemExit(f"{args.run_dir} is not a run of ours on peg_insertion_remove")
    replay = load_replay(args.run_dir, "reset", checkpoint=saved.checkpoint)
    rows = replay.storage[:min(replay.write_count, replay.storage.max_size)]
    examples = load_examples(args.run_dir, checkpoint=saved.checkpoint)
    model, actor = saved.reset.model, saved.reset.actor
    env = PegInsertionEnv("remove")
    env.reset(seed=0)
    obs = rows["observation"].float()
    d, z = peg_distances(env, obs)
    p_taken = trigger_probability(model, obs, rows["action"].float()).numpy()
    p_own = trigger_probability(model, obs, greedy_actions(actor, obs)).numpy()
    print(f"{args.run_dir} at {saved.checkpoint.name}: {len(obs)} reset replay rows (of {replay.write_count} written)")
    if len(examples):
        states = examples.states()["observation"].float()
        distinct = torch.unique(states, dim=0)
        de, _ = peg_distances(env, distinct)
        pe = trigger_probability(model, distinct, greedy_actions(actor, distinct)).numpy()
        print(f"examples: {len(states)} states, {len(distinct)} distinct; d_goal median {np.median(de):.3f}; "
              f"p with the reset actor's action: median {np.median(pe):.3f} (min {pe.min():.3f})")
    print("| d_goal (m) | rows | bottom below -0.45 | median p, action taken | median p, reset actor's action | "
          "p >= 0.1 (actor's) |")
    print("|---|---|---|---|---|---|")
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        m = (d >= lo) & (d < hi)
        if not m.any():
            print(f"| {lo:.1f}-{hi:.1f} | 0 | | | | |")
            continue
        print(f"| {lo:.1f}-{hi:.1f} | {int(m.sum())} | {float((z[m] < -0.45).mean()):.0%} | "
              f"{statistics.median(p_taken[m]):.3f} | {statistics.median(p_own[m]):.3f} | {float((p_own[m] >= 0.1).mean()):.0%} |")
    rho = np.corrcoef(np.argsort(np.argsort(d)), np.argsort(np.argsort(p_own)))[0, 1]
    print(f"rank correlation of d_goal and p (reset actor's action), all rows: {rho:+.2f}")


if __name__ == "__main__":
    main()
