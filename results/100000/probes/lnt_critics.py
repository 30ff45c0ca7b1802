"""The LNT reset agent's Q-ensemble on its own reset replay, from a run's checkpoint.

    python results/100000/probes/lnt_critics.py runs/peg_insertion_insert/lnt/seed1 100000
    python results/100000/probes/lnt_critics.py <run> <step> --csv series.csv   # also one row per call

Prints, for 4096 replay rows drawn uniformly and for the newest 4096 rows, the members' Q on the
replayed action and on the reset policy's action: the ensemble mean, the minimum over members (what
the trigger compares with Q_thresh), the spread between members, each member's mean, and each
member's TD(0) target and error as the update computes them. The shaped
reset reward lies in [0, 1], so every true value lies in [0, 1 / (1 - gamma)] = [0, 100].
"""
import argparse
from pathlib import Path

import torch

from torchrl_reset_recipes.training.reset_agents import lnt_batch
from torchrl_reset_recipes.analysis.saved_runs import load_agents, load_replay, run_config


def main(run: str, step: int, csv_path: str | None = None, rows: int = 4096) -> None:
    torch.set_num_threads(1)
    cfg = run_config(run)
    if cfg.algo.name not in ("lnt", "lnt_sparse"):
        raise SystemExit(f"{run} is an {cfg.algo.name} run; this probe reads LNT's Q-ensemble.")
    folder = Path(run) / "checkpoints" / f"step_{step:010d}"
    saved = load_agents(run, checkpoint=folder)
    cfg, agent = saved.cfg, saved.reset
    replay = load_replay(run, "reset", checkpoint=folder)
    held = len(replay)
    print(f"{run} at step {step}: {held} reset replay rows, {cfg.algo.num_members} members, "
          f"reward {cfg.algo.reset_reward}, Q_thresh {cfg.algo.threshold}")
    generator = torch.Generator().manual_seed(0)
    picks = {"uniform": torch.randint(0, held, (rows,), generator=generator),
             f"newest {rows}": torch.arange(max(0, held - rows), held)}
    summary = {"step": step, "rows": held, "q_thresh": float(cfg.algo.threshold)}
    for name, index in picks.items():
        data = replay.storage[index]
        reward = data["next", "reset_reward"] if cfg.algo.reset_reward == "shaped" else data["next", "reset_success"].float()
        print(f"{name}: reward mean {reward.mean():.3f}, rows at the start {data['next', 'reset_success'].float().mean():.3f}")
        with torch.no_grad():
            replayed = agent.model(data.select("observation", "action").clone())["state_action_value"]
            acting = agent.actor(data.select("observation").clone())
            policy = agent.model(acting.select("observation", "action"))["state_action_value"]
        for label, q in (("Q(s, a replayed)", replayed), ("Q(s, pi_r(s))", policy)):
            means, lowest = q.mean(0), q.amin(-1)
            stats = {"q_mean": q.mean().item(), "q_min_over_members": lowest.mean().item(),
                     "below_thresh": (lowest < cfg.algo.threshold).float().mean().item(),
                     "spread": q.std(-1).mean().item(), "lowest_member": means.min().item(),
                     "highest_member": means.max().item(),
                     "members_outside": int(((means < 0) | (means > 100)).sum())}
            print(f"  {label}: mean {stats['q_mean']:.1f}, minimum over members {stats['q_min_over_members']:.1f} "
                  f"(below Q_thresh on {stats['below_thresh']:.0%} of rows), "
                  f"spread (sd over members) {stats['spread']:.1f}; members outside [0, 100]: "
                  f"{stats['members_outside']} of {q.shape[-1]}")
            print("    member means: " + " ".join(f"{v:.0f}" for v in means.tolist()))
            if name == "uniform" and label == "Q(s, pi_r(s))":
                summary.update(stats, reward_mean=reward.mean().item())
        with torch.no_grad():  # the update's own TD(0) targets, from the target actor and critics
            out = agent.loss(lnt_batch(data.clone(), cfg.algo, int(cfg.algo.num_members)))
        error = (out["pred_value"] - out["target_value"]).pow(2).mean(0).sqrt()
        print("  TD(0) target, member means: " + " ".join(f"{v:.0f}" for v in out["target_value"].mean(0).tolist()))
        print("  TD(0) error (rms), members: " + " ".join(f"{v:.1f}" for v in error.tolist()))
        if name == "uniform":
            summary["td_rms_median"] = error.median().item()
    if csv_path:
        path = Path(csv_path)
        new = not path.exists()
        with path.open("a") as out:
            if new:
                out.write(",".join(summary) + "\n")
            out.write(",".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in summary.values()) + "\n")


def command_line(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", help="an LNT or LNT-sparse run folder written by recipes/train.py")
    parser.add_argument("step", type=int, help="the step of its checkpoint to read (checkpoints/step_<step>)")
    parser.add_argument("--csv", default=None, help="also appends one row of the summary to this CSV (a series)")
    args = parser.parse_args(argv)
    main(args.run, args.step, args.csv)


if __name__ == "__main__":
    command_line()
