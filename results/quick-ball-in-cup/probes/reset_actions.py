"""The reset agent's last actions, from a run's checkpoint: does the reset policy sit at the action bound?

    python results/quick-ball-in-cup/probes/reset_actions.py <run folder> [<run folder> ...] [--last 2000]

Reads the newest checkpoint's reset replay buffer (the actions as executed by the reset policy with its
exploration noise; with ``exploration.clip: false`` as drawn, so they may lie outside the action box) and
prints, over its last ``--last`` rows: the mean of |a|, the share of action entries outside [-1, 1], and
each action dimension's mean and standard deviation.
"""
import argparse
import sys
from pathlib import Path

from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "recipes"))
from buffers import make_buffers  # noqa: E402
from run_files import Checkpoints  # noqa: E402


def reset_actions(run: Path, last: int):
    cfg = OmegaConf.load(run / "config.yaml")
    folder = Checkpoints(run / "checkpoints").folders()[0]  # newest first
    _, reset_rb = make_buffers(cfg)
    reset_rb.loads(folder / "reset_buffer")
    return folder.name, reset_rb[:]["action"][-last:]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--last", type=int, default=2000)
    args = parser.parse_args()
    for run in args.runs:
        step, a = reset_actions(run, args.last)
        means = ", ".join(f"{v:+.2f}" for v in a.mean(0).tolist())
        stds = ", ".join(f"{v:.2f}" for v in a.std(0).tolist())
        print(f"{run} ({step}, last {len(a)} reset actions): mean |a| {a.abs().mean():.2f}; "
              f"outside [-1, 1] {100 * (a.abs() > 1).float().mean():.0f}%; mean ({means}); sd ({stds})")


if __name__ == "__main__":
    main()
