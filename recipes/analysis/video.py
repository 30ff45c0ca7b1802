"""An animated GIF of one evaluation of a trained run: a forward episode, then a reset episode.

    MUJOCO_GL=egl python recipes/analysis/video.py runs/ball_in_cup_catch-ours-0          # -> <run>/eval.gif
    MUJOCO_GL=egl python recipes/analysis/video.py RUN_DIR --out clip.gif --size 320 --fps 25

Loads the run's saved configuration and its latest checkpoint, and plays the evaluation of the
training recipe (exploration off, the reset trigger on during the forward episode): the forward
policy until the trigger fires or H_f steps, then the reset policy until the task's at-initial-state
check (after the minimum reset steps) or H_r steps. Each frame gets a coloured border: green while
the forward agent acts, blue while the reset agent acts, red on the step where the trigger stopped
the forward agent. Rendering is off-screen and needs an OpenGL backend (README, "Rendering"); the
UR3 tasks have no rendering.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


from torchrl_reset_recipes.analysis.saved_runs import load_agents
from torchrl_reset_recipes.training.task_envs import EVAL_SEED_OFFSET, evaluate, make_task_env

COLOURS = {"forward": (40, 170, 60), "reset": (40, 90, 220), "trigger": (220, 40, 40)}


def framed(frame: np.ndarray, phase: str, width: int = 4) -> np.ndarray:
    """The frame with a ``width``-pixel border in the colour of ``phase``."""
    out = frame.copy()
    colour = np.array(COLOURS[phase], dtype=np.uint8)
    out[:width], out[-width:], out[:, :width], out[:, -width:] = colour, colour, colour, colour
    return out


def record(run_dir: Path, *, size: int = 240) -> tuple[list[np.ndarray], dict]:
    """The frames of one evaluation of ``run_dir``'s latest checkpoint, and what happened in it."""
    saved = load_agents(run_dir)
    cfg, forward, reset = saved.cfg, saved.forward, saved.reset
    # make_env refuses render_mode for the UR3 tasks (no camera on the twin)
    env, trigger = make_task_env(saved.spec, reset, for_eval=True, render_mode="rgb_array", width=size, height=size)
    env.set_seed(int(cfg.seed) + EVAL_SEED_OFFSET)  # as the recipe's evaluation env

    frames = []
    info = evaluate(env, trigger, forward.actor, reset.actor, horizon=saved.spec.forward_horizon,
                    reset_horizon=saved.spec.reset_horizon, min_reset_steps=int(cfg.reset.min_steps), gamma=float(cfg.gamma),
                    observe=lambda phase: frames.append(framed(env.render(), phase)))
    info["checkpoint"] = saved.checkpoint.name
    env.close()
    return frames, info


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=Path, help="a run folder written by recipes/train.py")
    parser.add_argument("--out", type=Path, default=None, help="the GIF to write (default: <run_dir>/eval.gif)")
    parser.add_argument("--size", type=int, default=240, help="frame width and height in pixels")
    parser.add_argument("--fps", type=float, default=20.0, help="frames per second of the GIF")
    args = parser.parse_args(argv)
    if args.size < 16 or args.fps <= 0:
        parser.error("--size must be at least 16 and --fps positive")
    import imageio.v2 as imageio

    frames, info = record(args.run_dir, size=args.size)
    out = args.out or args.run_dir / "eval.gif"
    out.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(out, frames, duration=1000.0 / args.fps, loop=0)
    info.update(frames=len(frames), path=str(out))
    print(f"{out}: {len(frames)} frames from {info['checkpoint']}; forward {info['forward_steps']} steps"
          f"{' (trigger fired)' if info['triggered'] else ''}, reset {info['reset_steps']} steps"
          f" ({'reached the start' if info['reset_success'] else 'did not reach the start'}).")
    return info


if __name__ == "__main__":
    main()
