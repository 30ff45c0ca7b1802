"""Did the trigger come in time? Whether the states before a run's triggered resets could still be saved.

    python recipes/recoverable.py runs/tier2/cliff_cheetah/ours/seed0 --window 25000
    python recipes/recoverable.py results/100000-tier2/cliff_cheetah/*/seed0 --csv-dir /tmp/verdicts

On a task with irrecoverable states (the cliff tasks: the ditch past the edge), a trigger protects the
system only if the state it stops in can still be brought back. ``triggers.csv`` keeps the whole
observation before each trigger (the cliff tasks observe ``qpos`` and ``qvel``), so each state can be
tried again in the task's own model: from it, a set of open-loop action sequences runs for ``--horizon``
steps (``mujoco.rollout``, bit for bit the env's own steps), and the state is

- **lost**: the env's latched flag was already on (the system was in the ditch before the trigger);
- **saved**: at least one sequence keeps the system out of the ditch for the whole horizon and ends it on
  the floor's side of the edge (certain: the sequence that does it was found);
- **doomed**: none of the tried sequences does (an upper bound on the truly irrecoverable states: a
  closed-loop policy might save a state no open-loop sequence tried here saves; with the default horizon
  of 3 s a state over the edge, or racing at it faster than the floor's friction can stop, is doomed).

The sequences (``--candidates``, 128 by default): no torque; each corner of the action box, held
(64 for six motors); the rest smooth random sequences, an Ornstein-Uhlenbeck process as the agents'
exploration (theta 0.15, dt 0.05) with sigma 1 in units of the action bound, clipped to the box, seeded.
Observations are logged to 5 significant digits (and cliff-walker's velocities clipped to +-10, as it
observes them): the state tried is the logged one.

For each ``--window``-step stretch: the triggers, how many were lost, doomed and saved, the median x of the
saved ones, and the reset episodes started by a trigger that ended in the ditch all the same (the reset
agent lost a state, doomed or not). ``--csv-dir`` also writes each trigger's verdict.
"""
from __future__ import annotations

import argparse
import csv
import statistics
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from stretches import _k, _rows, markdown, run_task  # noqa: E402

__all__ = ["candidate_actions", "rollout_qpos", "escapes", "first_escape", "verdicts", "stretch_table", "main"]

VERDICTS = ("lost", "doomed", "saved")


def candidate_actions(env, count: int = 128, horizon: int = 60, seed: int = 0) -> np.ndarray:
    """``count`` open-loop action sequences for ``env``, ``[count, horizon, action size]``: zeros first, then
    the corners of the action box held (all of them while they fit in half of ``count``, else a random
    choice of them), then smooth random sequences (see the module's docstring); deterministic in ``seed``."""
    if count < 1 or horizon < 1:
        raise ValueError(f"count and horizon must be positive, got count={count!r}, horizon={horizon!r}")
    low = np.asarray(env.action_space.low, dtype=np.float64)
    high = np.asarray(env.action_space.high, dtype=np.float64)
    size = low.shape[0]
    rng = np.random.default_rng(seed)
    sequences = [np.zeros((1, horizon, size))]
    corners_wanted = min(count - 1, max(count // 2, 0))
    if corners_wanted > 0:
        if 2 ** size <= corners_wanted:
            signs = ((np.arange(2 ** size)[:, None] >> np.arange(size)) & 1).astype(bool)
        else:
            signs = rng.integers(0, 2, size=(corners_wanted, size)).astype(bool)
        corners = np.where(signs, high, low)
        sequences.append(np.repeat(corners[:, None, :], horizon, axis=1))
    rest = count - sum(len(s) for s in sequences)
    if rest > 0:
        theta, dt, sigma = 0.15, 0.05, 1.0
        noise = np.zeros((rest, size))
        steps = []
        for _ in range(horizon):
            noise = noise - theta * noise * dt + sigma * np.sqrt(dt) * rng.standard_normal((rest, size))
            steps.append(noise)
        half, middle = (high - low) / 2, (high + low) / 2
        sequences.append(np.clip(middle + half * np.stack(steps, axis=1), low, high))
    return np.concatenate(sequences)[:count]


def rollout_qpos(env, qpos, qvel, actions: np.ndarray) -> np.ndarray:
    """``env``'s configuration after each step of each sequence of ``actions`` (``[count, horizon, action
    size]``) from ``qpos`` and ``qvel``: ``[count, horizon, nq]``. The env's own model, ``frame_skip`` physics
    steps per action with the action held and clamped at the motors' range, as its :meth:`step` does."""
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
    return states[:, env.frame_skip - 1 :: env.frame_skip, start : start + model.nq]


def escapes(env, qpos, qvel, actions: np.ndarray) -> np.ndarray:
    """For each sequence of ``actions`` (``[count, horizon, action size]``), whether it keeps ``env``'s system,
    started at ``qpos`` and ``qvel``, out of the ditch (``env.in_ditch``) after every step and on the floor's
    side of the edge (``x <= edge``) after the last: one bool per sequence (all False from the ditch)."""
    if not hasattr(env, "in_ditch"):
        raise TypeError(f"{type(env).__name__} has no irrecoverable states to escape (no in_ditch)")
    if env.in_ditch(np.asarray(qpos)):
        return np.zeros(len(actions), dtype=bool)
    seen = rollout_qpos(env, qpos, qvel, actions)
    return ~env.in_ditch(seen).any(axis=1) & (seen[:, -1, 0] <= env.edge)


def first_escape(env, qpos, qvel, actions: np.ndarray, chunk: int = 16) -> int:
    """The index of the first sequence of ``actions`` that :func:`escapes` says saves the state, or -1 when none
    does; tried ``chunk`` sequences at a time, so that a state the first ones save costs only those."""
    for first in range(0, len(actions), chunk):
        saved = np.flatnonzero(escapes(env, qpos, qvel, actions[first : first + chunk]))
        if saved.size:
            return first + int(saved[0])
    return -1


def verdicts(run: Path, *, candidates: int = 128, horizon: int = 60, seed: int = 0) -> list[dict]:
    """Each trigger of ``run`` (a run folder of a task with irrecoverable states): its ``frames``, the x
    position before it, its verdict (``lost``, ``doomed`` or ``saved``) and, when saved, the first sequence of
    :func:`candidate_actions` that saves it (0: no torque)."""
    run = Path(run)
    cfg, spec = run_task(run)
    if spec is None:
        raise ValueError(f"{run}: no config.yaml naming a task this code knows")
    if not spec.has_irrecoverable:
        raise ValueError(f"{run}: task {spec.name} has no irrecoverable states: every trigger there is in time")
    env = spec.env_class(**spec.kwargs)
    nq, nv = env.model.nq, env.model.nv
    actions = candidate_actions(env, candidates, horizon, seed)
    out = []
    for t in _rows(run / "triggers.csv"):
        obs = np.array([float(v) for v in t["observation"].split()])
        if obs.shape != (nq + nv,):
            raise ValueError(f"{run}: a trigger at frame {t['frames']} logged {obs.size} observation entries, "
                             f"{spec.name} has {nq + nv} (qpos and qvel)")
        row = {"frames": int(t["frames"]), "x": float(obs[0]), "verdict": "lost", "saved_by": ""}
        if t.get("irrecoverable") != "1":
            saved = first_escape(env, obs[:nq], obs[nq:], actions)
            row["verdict"] = "saved" if saved >= 0 else "doomed"
            row["saved_by"] = saved if saved >= 0 else ""
        out.append(row)
    env.close()
    return out


def stretch_table(run: Path, found: list[dict], window: int, upto: int | None = None) -> list[dict]:
    """``window``-step stretches of ``run`` (as far as ``progress.csv`` goes, or ``upto``) with the verdicts
    ``found`` (:func:`verdicts`) counted in each, the saved triggers' median x, and the reset episodes that a
    trigger started and that ended in the ditch."""
    if window < 1:
        raise ValueError(f"window must be a positive number of steps, got {window!r}")
    progress = _rows(Path(run) / "progress.csv")
    if not progress:
        raise FileNotFoundError(f"{run} has no progress.csv rows: not a run folder, or nothing logged yet")
    resets = _rows(Path(run) / "resets.csv")
    last = int(progress[-1]["frames"]) if upto is None else min(upto, int(progress[-1]["frames"]))
    table = []
    for start in range(0, last - window + 1, window):
        end = start + window
        here = [v for v in found if start < v["frames"] <= end]
        saved_x = [v["x"] for v in here if v["verdict"] == "saved"]
        after = [r for r in resets if start < int(r["frames"]) <= end and r.get("started_by") == "triggered"]
        table.append({
            "steps": f"{_k(start)}-{_k(end)}", "triggers": len(here),
            **{verdict: sum(v["verdict"] == verdict for v in here) for verdict in VERDICTS},
            "saved: median x": f"{statistics.median(saved_x):.3g}" if saved_x else "",
            "triggered resets": len(after),
            "ended in the ditch": sum(r.get("irrecoverable") == "1" for r in after),
        })
    return table


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="run folders of a cliff task (with triggers.csv)")
    parser.add_argument("--window", type=int, default=25000, help="steps per stretch (default 25000)")
    parser.add_argument("--upto", type=int, default=None, help="the last step reported (default: as far as logged)")
    parser.add_argument("--horizon", type=int, default=60, help="steps each sequence runs (default 60: 3 s)")
    parser.add_argument("--candidates", type=int, default=128, help="action sequences tried (default 128)")
    parser.add_argument("--seed", type=int, default=0, help="the random sequences' seed")
    parser.add_argument("--csv-dir", type=Path, default=None, help="also write each run's verdicts here")
    args = parser.parse_args(argv)
    for name in ("window", "horizon", "candidates"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be a positive integer, got {getattr(args, name)}")
    for run in args.runs:
        try:
            found = verdicts(run, candidates=args.candidates, horizon=args.horizon, seed=args.seed)
            table = stretch_table(run, found, args.window, args.upto)
        except (ValueError, FileNotFoundError) as error:
            parser.exit(2, f"error: {error}\n")
        print(f"## {run}\n\n{markdown(table)}\n")
        if args.csv_dir is not None:
            args.csv_dir.mkdir(parents=True, exist_ok=True)
            name = "_".join(Path(run).resolve().parts[-3:]) + "_verdicts.csv"
            with open(args.csv_dir / name, "w", newline="") as f:
                writer = csv.DictWriter(f, ["frames", "x", "verdict", "saved_by"])
                writer.writeheader()
                writer.writerows(found)


if __name__ == "__main__":
    main()
