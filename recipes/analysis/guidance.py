"""Whether a run's reset classifiers point the way back: their score of the reset agent's own states, grouped by
how far each state lies from the nearest example of an initial state.

    python recipes/analysis/guidance.py runs/peg_insertion_remove/ours/seed0 --checkpoint checkpoints/step_0000100000
    python recipes/analysis/guidance.py runs/*/ours/seed0 --bins 8

RCE's classifiers are the reset agent's only signal: from the examples (``S*``) the recursion spreads value to the
states the reset agent has seen lead there. Where they guide, the score ``p`` (what ours' trigger reads: the
members' mean of ``C / (1 - C)``, ``C`` clipped to [0, 0.5]) rises as the states near the examples; where it is
flat away from them, the reset actor climbs nothing and finds the way back only by chance.

For each run of ours (at ``--checkpoint``, default its latest complete one; it must hold its buffers, so not a
kept state) this reads the reset replay rows and the example buffer, measures each row's distance to its nearest
example, and prints a Markdown table: the examples themselves, then the rows in ``--bins`` groups of equal size by
that distance, each with its median distance, the median ``p`` and the share at or above the trigger's threshold,
then the Spearman rank correlation of distance and ``p`` over all rows (negative: ``p`` rises towards the
examples). Distances are Euclidean in the observation, each entry divided by its standard deviation over the
replay rows (an entry that never varies is left as it is), so that positions and velocities weigh alike. ``p``
scores each state with the reset actor's own action, without exploration (``--taken``: the action the row took).
No update is made.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch

__all__ = ["nearest_distances", "spearman", "guidance_rows", "markdown", "guidance", "main"]


def nearest_distances(rows: torch.Tensor, examples: torch.Tensor, scale: torch.Tensor | None = None,
                      chunk: int = 4096) -> torch.Tensor:
    """Each row's Euclidean distance to its nearest example, every entry divided by ``scale`` first (default:
    none), ``chunk`` rows at a time (rows ``[N, D]``, examples ``[E, D]``, E >= 1)."""
    if rows.ndim != 2 or examples.ndim != 2 or rows.shape[1] != examples.shape[1]:
        raise ValueError(f"rows [N, D] and examples [E, D] with one D, got {tuple(rows.shape)} and {tuple(examples.shape)}")
    if not len(examples):
        raise ValueError("no example to measure a distance to")
    rows, examples = rows.double(), examples.double()
    if scale is not None:
        rows, examples = rows / scale.double(), examples / scale.double()
    return torch.cat([torch.cdist(rows[i:i + chunk], examples).min(dim=1).values for i in range(0, len(rows), chunk)])


def spearman(a: torch.Tensor, b: torch.Tensor) -> float:
    """Spearman's rank correlation (ties take their mean rank); NaN where either side is constant."""
    from scipy.stats import spearmanr

    if len(a) < 2 or bool((a == a[0]).all()) or bool((b == b[0]).all()):
        return math.nan
    return float(spearmanr(a.numpy(), b.numpy()).statistic)


def guidance_rows(distance: torch.Tensor, p: torch.Tensor, bins: int, threshold: float) -> list[dict]:
    """The rows sorted by distance and cut into ``bins`` groups of equal size (the first groups one larger where
    the sizes do not divide): per group its distance range, median distance, row count, median ``p`` and the
    share of ``p`` at or above ``threshold``."""
    if bins < 1:
        raise ValueError(f"bins must be at least 1, got {bins}")
    if distance.shape != p.shape or distance.ndim != 1:
        raise ValueError(f"one distance per p, got {tuple(distance.shape)} and {tuple(p.shape)}")
    order = torch.argsort(distance, stable=True)
    groups = []
    for idx in torch.tensor_split(order, min(bins, len(order))):
        d, q = distance[idx], p[idx]
        groups.append({"from": float(d.min()), "to": float(d.max()), "median_distance": _median(d),
                       "rows": len(idx), "median_p": _median(q), "at_or_above": float((q >= threshold).double().mean())})
    return groups


def _median(values: torch.Tensor) -> float:
    """The median, the mean of the two middle values for an even count (``torch.median`` takes the lower one)."""
    return float(torch.quantile(values.double(), 0.5))


def markdown(examples: dict, groups: list[dict], threshold: float) -> str:
    lines = [f"| distance to the nearest example | rows | median distance | median p | p >= {threshold:g} |",
             "|---|---|---|---|---|",
             f"| the examples ({examples['distinct']} distinct) | {examples['rows']} | 0 | {examples['median_p']:.3f} | "
             f"{examples['at_or_above']:.0%} |"]
    for g in groups:
        lines.append(f"| {g['from']:.2f}-{g['to']:.2f} | {g['rows']} | {g['median_distance']:.2f} | {g['median_p']:.3f} | "
                     f"{g['at_or_above']:.0%} |")
    return "\n".join(lines)


def guidance(run: Path, checkpoint: str | None = None, bins: int = 6, taken: bool = False) -> str:
    """The report of one run (see the module's text)."""
    from torchrl_reset_recipes.analysis.saved_runs import (greedy_actions, load_agents, load_examples, load_replay,
                                                           trigger_probability)

    saved = load_agents(run, checkpoint=checkpoint, agents=("reset",))
    if saved.spec.kind.name != "ours":
        raise SystemExit(f"{run} is a run of {saved.spec.kind.name}: this reads ours' classifiers")
    replay = load_replay(run, "reset", checkpoint=saved.checkpoint)
    rows = replay.storage[:min(replay.write_count, replay.storage.max_size)]
    examples = load_examples(run, checkpoint=saved.checkpoint).states()["observation"].float()
    model, actor, threshold = saved.reset.model, saved.reset.actor, saved.spec.trigger_threshold
    observation = rows["observation"].float().reshape(len(rows), -1)
    examples = examples.reshape(len(examples), -1)
    distinct = torch.unique(examples, dim=0)
    spread = observation.std(dim=0)
    scale = torch.where(spread > 0, spread, torch.ones_like(spread))
    distance = nearest_distances(observation, distinct, scale)
    action = rows["action"].float() if taken else greedy_actions(actor, observation)
    p = trigger_probability(model, observation, action)
    p_examples = trigger_probability(model, distinct, greedy_actions(actor, distinct))
    at_examples = {"distinct": len(distinct), "rows": len(examples), "median_p": _median(p_examples),
                   "at_or_above": float((p_examples >= threshold).double().mean())}
    chosen = "action taken" if taken else "reset actor's greedy action"
    head = (f"{run} at {saved.checkpoint.name}: {len(observation)} reset replay rows, p with the "
            f"{chosen}; distances in the observation, each entry "
            f"divided by its spread over these rows")
    rho = spearman(distance, p.double())
    return "\n".join([head, "", markdown(at_examples, guidance_rows(distance, p.double(), bins, threshold), threshold), "",
                      f"Spearman rank correlation of distance and p: {rho:+.2f}"])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run folders of ours")
    parser.add_argument("--checkpoint", default=None,
                        help="a checkpoint with its buffers (default: each run's latest complete one)")
    parser.add_argument("--bins", type=int, default=6, help="groups of rows by distance (default 6)")
    parser.add_argument("--taken", action="store_true", help="score the action each row took, not the reset actor's")
    args = parser.parse_args(argv)
    if args.bins < 1:
        parser.error("--bins must be at least 1")
    torch.set_num_threads(1)
    for i, run in enumerate(args.runs):
        print(("\n" if i else "") + guidance(run, args.checkpoint, args.bins, args.taken), flush=True)


if __name__ == "__main__":
    main()
