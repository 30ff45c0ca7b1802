"""Frozen: its question is decided. It last ran at commit 271779f, as results/quick-ball-in-cup/probes/min_member.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/quick-ball-in-cup/probes/min_member.py --help``.

Which member is the minimum the reset actor ascends, and what pulls its action: the trained part or the prior?

    python results/main-job/probes/min_member.py <run folder> [<run folder> ...] [--rows 2000]
    python results/main-job/probes/min_member.py <run folder> --every-checkpoint

Ours' reset actor ascends ``min_i C_i(s, pi(s))``; each member's logit is ``f_i(s, a) + beta g_i(s, a)`` with
``g_i`` a fixed random prior. On the newest ``--rows`` states of the newest checkpoint's reset replay, with
the actor's own (noiseless) action ``a = pi(s)``, this prints: how often each member is the minimum; the
gradient of the minimum member's logit with respect to the action, split into its trained part ``df/da``
and its prior part ``beta dg/da`` (means over rows); the share of rows where each part points further
out of the action box from ``a`` (``sign(a) * d/da > 0``, per action entry, where ``|a| > 0.9``); and how deep
the actor's tanh is saturated (its input beyond +-3, where the gradient through it is below 1%).
"""
import argparse
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[3]
from torchrl_reset_recipes.training.checkpoints import Checkpoints
from torchrl_reset_recipes.analysis.saved_runs import latest_checkpoint, load_agents, load_replay

from torchrl_reset import EnsembleValueOperator  # noqa: E402


def probe(run: Path, rows: int, folder: Path | None = None, brief: bool = False) -> None:
    folder = latest_checkpoint(run) if folder is None else folder
    torch.manual_seed(0)
    # the reference ensemble: its trained and prior parts can be read apart
    saved = load_agents(run, checkpoint=folder, overrides={"speed.accelerate": False}, agents=("reset",))
    agent = saved.reset
    replay = load_replay(run, "reset", checkpoint=folder)
    states = replay[:][-rows:].select("observation")
    model: EnsembleValueOperator = agent.model
    with torch.no_grad():
        acted = agent.actor(states.clone())
    action, pre = acted["action"], acted["action_preactivation"]  # a = tanh(pre) (scaled to the box)
    action = action.detach().requires_grad_(True)
    obs = states["observation"]
    f = model.members_forward(obs, action, *model.layer_tensors(agent.loss.classifier_network_params))
    g = model.members_forward(obs, action, *model.layer_tensors(agent.loss.classifier_network_params, "prior_"))
    logits = f + model.prior_scale * g  # [K, N]
    lowest = logits.argmin(0)
    pick = lowest.unsqueeze(0)
    f_min, g_min = f.gather(0, pick).sum(), g.gather(0, pick).sum()
    df = torch.autograd.grad(f_min, action, retain_graph=True)[0]
    dg = model.prior_scale * torch.autograd.grad(g_min, action)[0]
    k = logits.shape[0]
    edge = action.detach().abs() > 0.9
    if brief:
        print(f"{folder.name}: action mean ({', '.join(f'{v:+.2f}' for v in action.detach().mean(0).tolist())}), "
              f"|a| > 0.9 on {100 * edge.float().mean():.0f}%, tanh input beyond +-3 on {100 * (pre.abs() > 3).float().mean():.0f}% "
              f"(mean |.| {pre.abs().mean():.1f})")
        return
    shares = ", ".join(f"{100 * (lowest == i).float().mean():.0f}%" for i in range(k))
    outward = lambda d: 100 * ((torch.sign(action.detach()) * d) > 0)[edge].float().mean() if edge.any() else float("nan")  # noqa: E731
    print(f"{run} ({folder.name}, {len(obs)} states): the minimum member {shares} of rows (members 0-{k - 1}); "
          f"action mean ({', '.join(f'{v:+.2f}' for v in action.detach().mean(0).tolist())}), "
          f"|a| > 0.9 on {100 * edge.float().mean():.0f}% of entries; the tanh's input: mean |.| {pre.abs().mean():.1f}, "
          f"beyond +-3 (tanh' < 0.01: the actor's gradient all but gone) on {100 * (pre.abs() > 3).float().mean():.0f}%")
    print(f"  d(min logit)/da, trained part df/da: mean ({', '.join(f'{v:+.2f}' for v in df.mean(0).tolist())}), "
          f"|.| {df.abs().mean():.2f}; prior part beta dg/da: mean ({', '.join(f'{v:+.2f}' for v in dg.mean(0).tolist())}), "
          f"|.| {dg.abs().mean():.2f}")
    print(f"  where |a| > 0.9, pointing further out of the box: trained part {outward(df):.0f}%, prior part "
          f"{outward(dg):.0f}%, both together {outward(df + dg):.0f}%")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run folders of ours written by recipes/train.py")
    parser.add_argument("--rows", type=int, default=2000, help="the newest reset replay rows to read")
    parser.add_argument("--every-checkpoint", action="store_true",
                        help="one short line per checkpoint kept, oldest first (the actor's saturation over time)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    for run in args.runs:
        if args.every_checkpoint:
            for folder in reversed(Checkpoints(run / "checkpoints").folders()):
                probe(run, args.rows, folder, brief=True)
        else:
            probe(run, args.rows)


if __name__ == "__main__":
    main()
