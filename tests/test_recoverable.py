"""recipes/recoverable.py: whether a trigger's state could still be saved, tried in the task's own model."""
from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "recipes"))

import recoverable  # noqa: E402
from torchrl_reset_envs import CliffCheetahEnv, CliffWalkerEnv  # noqa: E402


@pytest.fixture(scope="module")
def cheetah():
    env = CliffCheetahEnv()
    env.reset(seed=0)
    yield env
    env.close()


def state(env, x: float, z: float = 0.0, vx: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The model's rest pose moved to ``x`` (and height ``z``), moving at ``vx`` along x."""
    qpos, qvel = env.model.qpos0.copy(), np.zeros(env.model.nv)
    qpos[0], qpos[1], qvel[0] = x, z, vx
    return qpos, qvel


def stopping_distance(env, v: float) -> float:
    """How far friction alone needs to stop a body sliding at ``v``: ``v^2 / (2 mu g)``, mu the largest friction
    coefficient of any geom (MuJoCo takes the larger of a contact's two), g the model's gravity."""
    mu = float(env.model.geom_friction[:, 0].max())
    return v**2 / (2 * mu * abs(float(env.model.opt.gravity[2])))


def test_the_candidates_are_no_torque_every_corner_then_random_sequences_in_the_box(cheetah):
    actions = recoverable.candidate_actions(cheetah, count=128, horizon=20, seed=3)
    assert actions.shape == (128, 20, 6)
    assert not actions[0].any()  # no torque first
    corners = actions[1:65]
    assert (corners == corners[:, :1]).all()  # each held for the whole horizon
    assert {tuple(c) for c in corners[:, 0]} == {tuple(s) for s in np.array(np.meshgrid(*[[-1.0, 1.0]] * 6)).reshape(6, -1).T}
    rest = actions[65:]
    assert (np.abs(rest) <= 1.0).all() and len({tuple(r[-1]) for r in rest}) == len(rest)
    assert np.array_equal(actions, recoverable.candidate_actions(cheetah, count=128, horizon=20, seed=3))
    assert not np.array_equal(actions, recoverable.candidate_actions(cheetah, count=128, horizon=20, seed=4))
    few = recoverable.candidate_actions(cheetah, count=9, horizon=5)
    assert few.shape == (9, 5, 6) and not few[0].any() and (np.abs(few[1:5]) == 1.0).all()
    assert recoverable.candidate_actions(cheetah, count=1, horizon=5).shape == (1, 5, 6)
    with pytest.raises(ValueError, match="positive"):
        recoverable.candidate_actions(cheetah, count=0)


def test_the_rollouts_are_the_envs_own_steps_and_escaping_is_staying_out_and_behind_the_edge(cheetah):
    actions = recoverable.candidate_actions(cheetah, count=24, horizon=40, seed=1)
    seen = []
    for qpos, qvel in (state(cheetah, 13.0, vx=6.0), state(cheetah, 10.0, vx=3.0)):
        trajectories = recoverable.rollout_qpos(cheetah, qpos, qvel, actions)
        verdict = recoverable.escapes(cheetah, qpos, qvel, actions)
        seen += verdict.tolist()
        for k in range(len(actions)):
            cheetah.reset(seed=0)  # clears the latched flag
            cheetah.set_state(qpos, qvel)
            for t, action in enumerate(actions[k]):
                _, _, _, _, info = cheetah.step(action)
                np.testing.assert_array_equal(trajectories[k, t], cheetah.data.qpos)
            assert verdict[k] == (not info["irrecoverable"] and cheetah.data.qpos[0] <= cheetah.edge), (qpos[0], k)
    assert any(seen) and not all(seen)  # both answers were compared
    # 0.25 s after racing over the edge at 12 m/s the body has fallen g t^2 / 2 = 0.31 m, not yet into the
    # ditch (1 m down): it has not escaped all the same, it ends past the edge
    short = recoverable.candidate_actions(cheetah, count=16, horizon=5)
    qpos, qvel = state(cheetah, 13.9, vx=12.0)
    assert not cheetah.in_ditch(recoverable.rollout_qpos(cheetah, qpos, qvel, short)).any()
    assert not recoverable.escapes(cheetah, qpos, qvel, short).any()


def test_what_physics_decides_is_what_the_check_finds(cheetah):
    actions = recoverable.candidate_actions(cheetah)
    # at rest 9 m before the edge nothing moves it there: no torque saves it
    assert recoverable.first_escape(cheetah, *state(cheetah, 5.0), actions) == 0
    # already in the ditch: nothing saves it
    assert not recoverable.escapes(cheetah, *state(cheetah, 15.0, z=-1.5), actions).any()
    # racing at the edge faster than friction can stop it before the edge
    for x, v in ((13.9, 12.0), (12.0, 6.0)):
        assert cheetah.edge - x < stopping_distance(cheetah, v) / 2
        assert recoverable.first_escape(cheetah, *state(cheetah, x, vx=v), actions) == -1
    walker = CliffWalkerEnv()
    walker.reset(seed=0)
    assert recoverable.first_escape(walker, *state(walker, 0.0, z=walker.model.qpos0[1]), actions[:8]) >= 0
    assert recoverable.first_escape(walker, *state(walker, 7.0, z=-1.0), actions[:8]) == -1
    walker.close()
    with pytest.raises(TypeError, match="no irrecoverable"):
        from torchrl_reset_envs import PegInsertionEnv
        recoverable.escapes(PegInsertionEnv(), np.zeros(7), np.zeros(7), actions[:1])


def write(path: Path, fields: list[str], rows: list[list]) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(fields)
        writer.writerows(rows)


def observation(env, x, z=0.0, vx=0.0) -> str:
    return " ".join(f"{v:.5g}" for v in np.concatenate(state(env, x, z, vx)))


def cliff_run(root: Path, env, task: str = "cliff_cheetah") -> Path:
    root.mkdir()
    (root / "config.yaml").write_text(f"task:\n  name: {task}\n")
    write(root / "progress.csv", ["frames", "forward_steps"], [[1000, 600], [2000, 1200], [2500, 1500]])
    # a trigger at rest (saved), one already in the ditch (the flag on: lost), one racing at the edge (doomed)
    write(root / "triggers.csv", ["frames", "steps", "value", "irrecoverable", "observation"], [
        [300, 30, 5.0, 0, observation(env, 5.0)], [800, 80, 15.0, 1, observation(env, 15.0, z=-1.5)],
        [1500, 150, 13.9, 0, observation(env, 13.9, vx=12.0)],
    ])
    write(root / "resets.csv", ["frames", "outcome", "steps", "started_by", "irrecoverable"], [
        [400, "success", 100, "triggered", 0], [900, "manual", 100, "triggered", 1],
        [1100, "manual", 200, "requested", 1], [1600, "manual", 100, "triggered", 1],
    ])
    return root


def test_verdicts_per_trigger_and_per_stretch(tmp_path, cheetah, capsys):
    run = cliff_run(tmp_path / "run", cheetah)
    found = recoverable.verdicts(run, candidates=16, horizon=40)
    assert [(v["frames"], v["verdict"], v["saved_by"]) for v in found] == [
        (300, "saved", 0), (800, "lost", ""), (1500, "doomed", "")]
    table = recoverable.stretch_table(run, found, window=1000)
    # 0-1k: the saved trigger (x = 5) and the lost one; resets a trigger started ending at 400 (out) and 900 (in
    # the ditch); the reset at 1100 followed a forward episode that ran to its horizon, not a trigger
    assert table == [
        {"steps": "0-1k", "triggers": 2, "lost": 1, "doomed": 0, "saved": 1, "saved: median x": "5",
         "triggered resets": 2, "ended in the ditch": 1},
        {"steps": "1k-2k", "triggers": 1, "lost": 0, "doomed": 1, "saved": 0, "saved: median x": "",
         "triggered resets": 1, "ended in the ditch": 1},
    ]
    recoverable.main([str(run), "--window", "1000", "--candidates", "16", "--horizon", "40",
                      "--csv-dir", str(tmp_path / "out")])
    assert "| 0-1k | 2 | 1 | 0 | 1 | 5 | 2 | 1 |" in capsys.readouterr().out
    (written,) = (tmp_path / "out").iterdir()
    assert [r["verdict"] for r in csv.DictReader(open(written))] == ["saved", "lost", "doomed"]


def test_bad_input_is_refused_with_a_reason(tmp_path, cheetah, capsys):
    peg = cliff_run(tmp_path / "peg", cheetah, task="peg_insertion_insert")
    with pytest.raises(ValueError, match="no irrecoverable states"):
        recoverable.verdicts(peg)
    short = cliff_run(tmp_path / "short", cheetah)
    write(short / "triggers.csv", ["frames", "steps", "value", "irrecoverable", "observation"], [[1, 1, 0.0, 0, "1 2 3"]])
    with pytest.raises(ValueError, match="3 observation entries"):
        recoverable.verdicts(short)
    with pytest.raises(SystemExit):
        recoverable.main([str(tmp_path / "nothing-here")])
    assert "no config.yaml" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        recoverable.main([str(peg), "--horizon", "0"])
