"""recipes/analysis/recoverable.py: whether a trigger's state could still be saved, tried in the task's own model."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest


from torchrl_reset_recipes.analysis import recoverable
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
    actions = recoverable.candidate_actions(cheetah, count=128, steps=20, seed=3)
    assert actions.shape == (128, 20, 6)
    assert not actions[0].any()  # no torque first
    corners = actions[1:65]
    assert (corners == corners[:, :1]).all()  # each held for the whole horizon
    assert {tuple(c) for c in corners[:, 0]} == {tuple(s) for s in np.array(np.meshgrid(*[[-1.0, 1.0]] * 6)).reshape(6, -1).T}
    rest = actions[65:]
    assert (np.abs(rest) <= 1.0).all() and len({tuple(r[-1]) for r in rest}) == len(rest)
    assert np.array_equal(actions, recoverable.candidate_actions(cheetah, count=128, steps=20, seed=3))
    assert not np.array_equal(actions, recoverable.candidate_actions(cheetah, count=128, steps=20, seed=4))
    few = recoverable.candidate_actions(cheetah, count=9, steps=5)
    assert few.shape == (9, 5, 6) and not few[0].any() and (np.abs(few[1:5]) == 1.0).all()
    some = recoverable.candidate_actions(cheetah, count=101, steps=2)[1:51, 0]  # 50 of the 64 corners
    assert (np.abs(some) == 1.0).all() and len({tuple(c) for c in some}) == 50  # all different
    assert recoverable.candidate_actions(cheetah, count=1, steps=5).shape == (1, 5, 6)
    with pytest.raises(ValueError, match="positive"):
        recoverable.candidate_actions(cheetah, count=0)


@pytest.mark.parametrize("task", ["cheetah", "walker"])
def test_the_rollouts_are_the_envs_own_steps_and_escaping_is_staying_out_and_behind_the_edge(cheetah, task):
    env = cheetah if task == "cheetah" else CliffWalkerEnv()
    actions = recoverable.candidate_actions(env, count=24 if task == "cheetah" else 8, steps=40, seed=1)
    z = 0.0 if task == "cheetah" else float(env.model.qpos0[1])
    cases = [state(env, env.edge - 1.0, z, vx=6.0), state(env, env.edge - 4.0, z, vx=3.0)]
    mu = float(env.model.geom_friction[:, 0].max())
    seen = []
    for qpos, qvel in cases:
        positions, velocities = recoverable.rollout(env, qpos, qvel, actions)
        verdict = recoverable.escapes(env, qpos, qvel, actions)
        seen += verdict.tolist()
        for k in range(len(actions)):
            env.reset(seed=0)  # clears the latched flag and the solver's warm start
            env.set_state(qpos, qvel)
            for t, action in enumerate(actions[k]):
                _, _, _, _, info = env.step(action)
                np.testing.assert_array_equal(positions[k, t], env.data.qpos)
                np.testing.assert_array_equal(velocities[k, t], env.data.qvel)
            x, vx = env.data.qpos[0], env.data.qvel[0]
            behind = x <= env.edge and (vx <= 0 or env.edge - x > vx**2 / (2 * mu * 9.81))
            assert verdict[k] == (not info["irrecoverable"] and behind), (qpos[0], k)
    if task == "cheetah":
        assert any(seen) and not all(seen)  # both answers were compared
        # one step (0.05 s) after racing over the edge at 12 m/s the body is about 0.6 m past it and nowhere near
        # the ditch's floor 1 m down: it has not escaped all the same, it ends past the edge
        short = recoverable.candidate_actions(env, count=16, steps=1)
        qpos, qvel = state(env, 13.9, vx=12.0)
        positions = recoverable.rollout(env, qpos, qvel, short)[0]
        assert not env.in_ditch(positions).any() and (positions[:, -1, 0] > env.edge).all()
        assert not recoverable.escapes(env, qpos, qvel, short).any()
    else:
        env.close()


def test_a_body_left_behind_the_edge_but_racing_at_it_has_not_escaped(cheetah):
    """At the end of the horizon the body must be moving away from the edge or farther from it than friction
    needs to stop it: a cheetah 0.5 m before the edge at 5 m/s after a one-step horizon (it moves about 0.25 m
    in 0.05 s) is still behind the edge, but v^2 / (2 mu g) = 3.2 m > 0.5 m; at rest there it has escaped."""
    one = recoverable.candidate_actions(cheetah, count=1, steps=1)
    assert recoverable.stopping_distance(cheetah, 5.0) == pytest.approx(25 / (2 * 0.4 * 9.81))
    racing = recoverable.rollout(cheetah, *state(cheetah, 13.5, vx=5.0), one)[0]
    assert racing[0, -1, 0] < cheetah.edge
    assert not recoverable.escapes(cheetah, *state(cheetah, 13.5, vx=5.0), one).any()
    assert recoverable.escapes(cheetah, *state(cheetah, 13.5), one).all()


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
    with pytest.raises(TypeError, match="no ditch"):
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
    # triggers at rest (saved), one already in the ditch (the flag on: lost), one racing at the edge (doomed)
    # each trigger's reset episode starts at its frame (frames - steps); one more saved trigger whose reset
    # fell in all the same, and a reset after a forward episode that ran to its horizon
    write(root / "triggers.csv", ["frames", "steps", "value", "irrecoverable", "observation"], [
        [300, 30, 5.0, 0, observation(env, 5.0)], [800, 80, 15.0, 1, observation(env, 15.0, z=-1.5)],
        [950, 60, 6.0, 0, observation(env, 6.0)], [1500, 150, 13.9, 0, observation(env, 13.9, vx=12.0)],
    ], )
    write(root / "resets.csv", ["frames", "outcome", "steps", "started_by", "irrecoverable"], [
        [400, "success", 100, "triggered", 0], [900, "manual", 100, "triggered", 1],
        [990, "manual", 40, "triggered", 1], [1100, "manual", 110, "requested", 1],
        [1600, "manual", 100, "triggered", 1],
    ])
    return root


def test_verdicts_per_trigger_and_per_stretch(tmp_path, cheetah, capsys):
    run = cliff_run(tmp_path / "run", cheetah)
    found = recoverable.verdicts(run, candidates=16, horizon=40)
    assert [(v["frames"], v["verdict"], v["saved_by"]) for v in found] == [
        (300, "saved", 0), (800, "lost", ""), (950, "saved", 0), (1500, "doomed", "")]
    table = recoverable.stretch_table(run, found, window=1000)
    # 0-1k: two saved triggers (x = 5 and 6: median 5.5) and the lost one; of the saved ones' resets (from 300 and
    # from 950) the second ended in the ditch; the lost trigger's reset (from 800) is not counted with them
    assert table == [
        {"steps": "0-1k", "triggers": 3, "lost": 1, "doomed": 0, "saved": 2, "saved: median x": "5.5",
         "saved, then lost in the reset": 1},
        {"steps": "1k-2k", "triggers": 1, "lost": 0, "doomed": 1, "saved": 0, "saved: median x": "",
         "saved, then lost in the reset": 0},
    ]
    recoverable.main([str(run), "--window", "1000", "--candidates", "16", "--horizon", "2",
                      "--csv-dir", str(tmp_path / "out")])
    assert "| 0-1k | 3 | 1 | 0 | 2 | 5.5 | 1 |" in capsys.readouterr().out
    (written,) = (tmp_path / "out").iterdir()
    assert [r["verdict"] for r in csv.DictReader(open(written))] == ["saved", "lost", "saved", "doomed"]
    # a state in the ditch whose flag was not logged (older runs: an empty column) is lost all the same
    rows = list(csv.reader(open(run / "triggers.csv")))
    rows[2][3] = ""
    write(run / "triggers.csv", rows[0], rows[1:])
    assert recoverable.verdicts(run, candidates=16, horizon=2.0)[1]["verdict"] == "lost"


def test_bad_input_is_refused_with_a_reason(tmp_path, cheetah, capsys):
    peg = cliff_run(tmp_path / "peg", cheetah, task="peg_insertion_insert")
    with pytest.raises(ValueError, match="no ditch"):
        recoverable.verdicts(peg)
    reacher = cliff_run(tmp_path / "reacher", cheetah, task="ur3_reacher")  # irrecoverable states, no ditch
    with pytest.raises(ValueError, match="cliff tasks"):
        recoverable.verdicts(reacher)
    short = cliff_run(tmp_path / "short", cheetah)
    write(short / "triggers.csv", ["frames", "steps", "value", "irrecoverable", "observation"], [[1, 1, 0.0, 0, "1 2 3"]])
    with pytest.raises(ValueError, match="3 observation entries"):
        recoverable.verdicts(short)
    with pytest.raises(SystemExit):
        recoverable.main([str(tmp_path / "nothing-here")])
    assert "no progress.csv" in capsys.readouterr().err
    cliff = cliff_run(tmp_path / "cliff", cheetah)
    with pytest.raises(SystemExit):
        recoverable.main([str(cliff), "--horizon", "0"])
    assert "--horizon must be a positive number of seconds" in capsys.readouterr().err
    (cliff / "progress.csv").unlink()  # found before any state is tried
    with pytest.raises(SystemExit):
        recoverable.main([str(cliff)])
    assert "no progress.csv" in capsys.readouterr().err
    write(cliff / "progress.csv", ["frames"], [[1000]])
    (cliff / "config.yaml").rename(cliff / "elsewhere.yaml")
    with pytest.raises(ValueError, match="no config.yaml"):
        recoverable.verdicts(cliff)
    (cliff / "elsewhere.yaml").rename(cliff / "config.yaml")
    write(cliff / "triggers.csv", ["frames", "steps", "value"], [[1, 1, 0.0]])
    with pytest.raises(ValueError, match="no observation"):
        recoverable.verdicts(cliff)
