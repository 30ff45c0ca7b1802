"""Did the trigger come in time? Whether the states before a run's triggered resets could still be saved.

    python recipes/analysis/recoverable.py runs/tier2/cliff_cheetah/ours/seed0 --window 25000
    python recipes/analysis/recoverable.py results/table1-cliff-cheetah/cliff_cheetah/*/seed0 --csv-dir /tmp/verdicts

On the cliff tasks a trigger protects the system only if the state it stops in can still be brought
back. ``triggers.csv`` keeps the whole observation before each trigger (the cliff tasks observe
``qpos`` and ``qvel``), so each state can be tried again in the task's own model: from it, a set of
open-loop action sequences runs for ``--horizon`` seconds (``mujoco.rollout``, the env's own steps:
the same numbers from a state set as after a reset), and the state is

- **lost**: already in the ditch (the env's latched flag was on, or the logged state is in it);
- **saved**: a sequence was found that keeps the body out of the ditch for the whole horizon and leaves it
  behind the edge, not heading over it (moving away from it, or farther from it than friction needs to stop
  it: ``edge - x > vx^2 / (2 mu g)``, mu the model's largest friction coefficient);
- **doomed**: none of the tried sequences does that. A closed-loop policy might save a state no open-loop
  sequence tried here saves, so "doomed" says that this search found no way out, not that none exists.

The sequences (``--candidates``, 128 by default): no torque; each corner of the action box, held
(64 for six motors); the rest smooth random sequences, an Ornstein-Uhlenbeck process as the agents'
exploration (theta 0.15, dt 0.05) with sigma 1 in units of the action bound, clipped to the box, seeded.
Observations are logged to 5 significant digits (and cliff-walker's velocities clipped to +-10, as it
observes them): the state tried is the logged one. The horizon is in seconds: 3 s is 60 steps of
cliff-cheetah, 300 of cliff-walker. Measured per state on one core beside two training runs, 3 s:
cheetah 0.07 s when no torque saves it, 0.45 s when doomed; walker 0.67 s and 8.5 s.

For each ``--window``-step stretch (a trigger in the stretch where it fired): the triggers, how many were
lost, doomed and saved, the median x of the saved ones, and how many saved ones the reset episode that
followed lost all the same (it ended in the ditch: the reset agent's failure, not the trigger's; a reset
is paired with its trigger by its start, ``frames - steps`` of ``resets.csv``). ``--csv-dir`` also writes
each trigger's verdict.
"""
from __future__ import annotations

import argparse
import csv
import statistics
from pathlib import Path

import numpy as np


from torchrl_reset_recipes.analysis.stretches import thousands, csv_rows, markdown, resets_by_start, run_task, within

__all__ = ["candidate_actions", "rollout", "stopping_distance", "escapes", "first_escape", "verdicts", "stretch_table", "main"]

VERDICTS = ("lost", "doomed", "saved")


def candidate_actions(env, count: int = 128, steps: int = 60, seed: int = 0) -> np.ndarray:
    """``count`` open-loop action sequences of ``steps`` steps for ``env``, ``[count, steps, action size]``: zeros
    first, then the corners of the action box held (all of them while they fit in half of ``count``, else as
    many different ones drawn at random), then smooth random sequences (see the module's docstring);
    deterministic in ``seed``."""
    if count < 1 or steps < 1:
        raise ValueError(f"count and steps must be positive, got count={count!r}, steps={steps!r}")
    low = np.asarray(env.action_space.low, dtype=np.float64)
    high = np.asarray(env.action_space.high, dtype=np.float64)
    size = low.shape[0]
    rng = np.random.default_rng(seed)
    sequences = [np.zeros((1, steps, size))]
    corners_wanted = min(count - 1, count // 2)
    if corners_wanted > 0:
        chosen = np.arange(2 ** size) if 2 ** size <= corners_wanted else rng.choice(2 ** size, corners_wanted, replace=False)
        signs = ((chosen[:, None] >> np.arange(size)) & 1).astype(bool)
        corners = np.where(signs, high, low)
        sequences.append(np.repeat(corners[:, None, :], steps, axis=1))
    rest = count - sum(len(s) for s in sequences)
    if rest > 0:
        theta, dt, sigma = 0.15, 0.05, 1.0
        noise = np.zeros((rest, size))
        drawn = []
        for _ in range(steps):
            noise = noise - theta * noise * dt + sigma * np.sqrt(dt) * rng.standard_normal((rest, size))
            drawn.append(noise)
        half, middle = (high - low) / 2, (high + low) / 2
        sequences.append(np.clip(middle + half * np.stack(drawn, axis=1), low, high))
    return np.concatenate(sequences)[:count]


def rollout(env, qpos, qvel, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``env``'s configuration and velocity after each step of each sequence of ``actions`` (``[count, horizon,
    action size]``) from ``qpos`` and ``qvel``: ``([count, horizon, nq], [count, horizon, nv])``. The env's own
    model, ``frame_skip`` physics steps per action with the action held and clamped at the motors' range, as
    its :meth:`step` does."""
    import mujoco
    import mujoco.rollout

    model = env.model
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = np.asarray(qpos, dtype=np.float64), np.asarray(qvel, dtype=np.float64)
    mujoco.mj_forward(model, data)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state = np.empty(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, state, spec)
    ctrl = np.repeat(np.clip(actions, env._ctrl_low, env._ctrl_high), env.frame_skip, axis=1)
    states, _ = mujoco.rollout.rollout(model, data, np.repeat(state[None], len(actions), axis=0), ctrl)
    start = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_TIME)  # the state vector: time, qpos, qvel, ...
    after = states[:, env.frame_skip - 1 :: env.frame_skip]
    return after[..., start : start + model.nq], after[..., start + model.nq : start + model.nq + model.nv]


def stopping_distance(env, velocity) -> np.ndarray:
    """How far friction alone needs to stop a body sliding at ``velocity``: ``v^2 / (2 mu g)``, mu the model's
    largest friction coefficient (MuJoCo takes the larger of a contact's two), g its gravity."""
    mu = float(env.model.geom_friction[:, 0].max())
    return np.asarray(velocity) ** 2 / (2 * mu * abs(float(env.model.opt.gravity[2])))


def escapes(env, qpos, qvel, actions: np.ndarray) -> np.ndarray:
    """For each sequence of ``actions`` (``[count, horizon, action size]``), whether it keeps ``env``'s system,
    started at ``qpos`` and ``qvel``, out of the ditch (``env.in_ditch``) after every step and leaves it behind
    the edge, not heading over it (``vx <= 0``, or ``edge - x`` more than :func:`stopping_distance`): one bool
    per sequence (all False from the ditch)."""
    if not hasattr(env, "in_ditch"):
        raise TypeError(f"{type(env).__name__} has no ditch to escape (no in_ditch): only the cliff tasks")
    if env.in_ditch(np.asarray(qpos)):
        return np.zeros(len(actions), dtype=bool)
    positions, velocities = rollout(env, qpos, qvel, actions)
    x, vx = positions[:, -1, 0], velocities[:, -1, 0]
    behind = (x <= env.edge) & ((vx <= 0) | (env.edge - x > stopping_distance(env, vx)))
    return ~env.in_ditch(positions).any(axis=1) & behind


def first_escape(env, qpos, qvel, actions: np.ndarray, chunk: int = 16) -> int:
    """The index of the first sequence of ``actions`` that :func:`escapes` says saves the state, or -1 when none
    does; tried ``chunk`` sequences at a time, so that a state the first ones save costs only those."""
    for first in range(0, len(actions), chunk):
        saved = np.flatnonzero(escapes(env, qpos, qvel, actions[first : first + chunk]))
        if saved.size:
            return first + int(saved[0])
    return -1


def _task_env(run: Path):
    cfg, spec = run_task(run)
    if spec is None:
        raise ValueError(f"{run}: no config.yaml naming a task this code knows")
    if not hasattr(spec.env_class, "in_ditch"):
        raise ValueError(f"{run}: task {spec.name} has no ditch to fall into: this check is for the cliff tasks")
    return spec.env_class(**spec.kwargs)


def verdicts(run: Path, *, candidates: int = 128, horizon: float = 3.0, seed: int = 0,
             progress: bool = False) -> list[dict]:
    """Each trigger of ``run`` (a run folder of a cliff task): its ``frames``, the x position before it, its
    verdict (``lost``, ``doomed`` or ``saved``, over ``horizon`` seconds) and, when saved, the first sequence of
    :func:`candidate_actions` that saves it (0: no torque). ``progress``: a progress bar over the triggers."""
    from tqdm import tqdm

    run = Path(run)
    env = _task_env(run)
    nq, nv = env.model.nq, env.model.nv
    actions = candidate_actions(env, candidates, max(1, round(horizon / env.dt)), seed)
    out = []
    for t in tqdm(csv_rows(run / "triggers.csv"), desc=f"{run}: trigger states", unit="state", disable=not progress,
                  mininterval=2.0, dynamic_ncols=True):
        if not t.get("observation"):
            raise ValueError(f"{run}/triggers.csv logs no observation (frame {t.get('frames')}): written by older code")
        obs = np.array([float(v) for v in t["observation"].split()])
        if obs.shape != (nq + nv,):
            raise ValueError(f"{run}: a trigger at frame {t['frames']} logged {obs.size} observation entries, "
                             f"the task has {nq + nv} (qpos and qvel)")
        row = {"frames": int(t["frames"]), "x": float(obs[0]), "verdict": "lost", "saved_by": ""}
        if t.get("irrecoverable") != "1" and not env.in_ditch(obs[:nq]):
            saved = first_escape(env, obs[:nq], obs[nq:], actions)
            row["verdict"] = "saved" if saved >= 0 else "doomed"
            row["saved_by"] = saved if saved >= 0 else ""
        out.append(row)
    env.close()
    return out


def stretch_table(run: Path, found: list[dict], window: int, upto: int | None = None) -> list[dict]:
    """``window``-step stretches of ``run`` (as far as ``progress.csv`` goes, or ``upto``) with the verdicts
    ``found`` (:func:`verdicts`) counted where each trigger fired, the saved triggers' median x, and how many
    saved triggers' reset episodes (paired by their start) ended in the ditch."""
    if window < 1:
        raise ValueError(f"window must be a positive number of steps, got {window!r}")
    progress = _progress(run)
    after = resets_by_start(run)
    last = int(progress[-1]["frames"]) if upto is None else min(upto, int(progress[-1]["frames"]))
    table = []
    for start in range(0, last - window + 1, window):
        end = start + window
        here = [v for v in found if within(v["frames"], start, end)]
        saved = [v for v in here if v["verdict"] == "saved"]
        table.append({
            "steps": f"{thousands(start)}-{thousands(end)}", "triggers": len(here),
            **{verdict: sum(v["verdict"] == verdict for v in here) for verdict in VERDICTS},
            "saved: median x": f"{statistics.median(v['x'] for v in saved):.3g}" if saved else "",
            "saved, then lost in the reset": sum(after.get(v["frames"], {}).get("irrecoverable") == "1" for v in saved),
        })
    return table


def _progress(run: Path) -> list[dict]:
    progress = csv_rows(Path(run) / "progress.csv")
    if not progress:
        raise FileNotFoundError(f"{run} has no progress.csv rows: not a run folder, or nothing logged yet")
    return progress


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run folders of a cliff task (with triggers.csv)")
    parser.add_argument("--window", type=int, default=25000, help="steps per stretch (default 25000)")
    parser.add_argument("--upto", type=int, default=None, help="the last step reported (default: as far as logged)")
    parser.add_argument("--horizon", type=float, default=3.0, help="seconds each sequence runs (default 3)")
    parser.add_argument("--candidates", type=int, default=128, help="action sequences tried (default 128)")
    parser.add_argument("--seed", type=int, default=0, help="the random sequences' seed")
    parser.add_argument("--csv-dir", type=Path, default=None, help="also write each run's verdicts here")
    args = parser.parse_args(argv)
    for name in ("window", "candidates"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be a positive integer, got {getattr(args, name)}")
    if not args.horizon > 0:
        parser.error(f"--horizon must be a positive number of seconds, got {args.horizon}")
    for run in args.runs:
        try:
            _progress(run)  # the cheap checks first
            found = verdicts(run, candidates=args.candidates, horizon=args.horizon, seed=args.seed, progress=True)
            table = stretch_table(run, found, args.window, args.upto)
        except (ValueError, FileNotFoundError) as error:
            parser.exit(2, f"error: {error}\n")
        print(f"## {run}\n\n{markdown(table)}\n")
        if args.csv_dir is not None:
            args.csv_dir.mkdir(parents=True, exist_ok=True)
            name = "_".join(part for part in Path(run).parts if part not in ("/", ".", "..")) + "_verdicts.csv"
            with open(args.csv_dir / name, "w", newline="") as f:
                writer = csv.DictWriter(f, ["frames", "x", "verdict", "saved_by"])
                writer.writeheader()
                writer.writerows(found)


if __name__ == "__main__":
    main()
