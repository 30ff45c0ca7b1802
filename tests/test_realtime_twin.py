"""The UR3 twin in wall-clock time (``env.backend=sim_realtime``) and what a run measures on a real-time arm:
overruns, the control period's histogram, each agent's updates against Algorithm 1's count. Times come from a
fake clock where a test asserts them; the one test on the real clock asserts counts with room for a loaded
machine."""
from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from torchrl_reset_envs import UR3Env
from torchrl_reset_envs.ur3_backends import SimRealtimeBackend

from helpers import quick_config

PERIOD = 0.04


class FakeClock:
    """A monotonic clock that moves only when the test computes (``advance``) or the backend sleeps."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        assert seconds >= 0
        self.t += seconds

    def advance(self, seconds: float) -> None:
        self.t += seconds


def twin(clock: FakeClock) -> UR3Env:
    return UR3Env("reacher", backend=SimRealtimeBackend("reacher", clock=clock, sleep=clock.sleep, period=PERIOD))


def test_the_twin_paces_steps_on_its_clock_and_counts_late_steps_as_overruns():
    clock = FakeClock()
    env = twin(clock)
    td = env.reset()
    sim_start, wall_start = float(env.backend.data.time), clock()
    computes = [0.010] * 5 + [0.065] + [0.010] * 4  # one step comes back 65 ms after its command: late
    for compute in computes:
        td = env.step(td.set("action", torch.full((6,), 0.1)))["next"].select("observation")
        assert env.time_left() == pytest.approx(PERIOD)  # the step returns at the start of a new period
        clock.advance(compute)
        td.set("action", torch.zeros(6))
    assert env.overruns == 1
    # by hand: a step sends its command when called and returns at the end of its period; a 10 ms compute fits
    # in the next period, so steps 1-6 end at 40, 80, ..., 240 ms. After step 6 the trainer takes 65 ms: step 7
    # is called at 305 ms, 25 ms after its period ended (280 ms): an overrun, and its period restarts then, so it
    # ends at 345 ms; steps 8-10 end at 385, 425 and 465 ms, and the last compute brings the clock to 475 ms
    elapsed = clock() - wall_start
    assert elapsed == pytest.approx(0.475)
    # the arm ran the whole time, the trainer's busy time included: the physics covers the wall-clock span to the
    # last step's end (465 ms), to the 2 ms physics step
    assert float(env.backend.data.time) - sim_start == pytest.approx(0.465, abs=0.002)
    # commands sent at 0, 50, 90, 130, 170, 210, 305, 355, 395, 435 ms: periods 50, 40 x 4, 95, 50, 40, 40 ms; the
    # median 40 ms and the 99th percentile 95 ms, each the upper edge of its 0.5 ms bin
    stats = env.control_period_stats()
    assert stats["measured"] == 9
    assert stats["median_ms"] == pytest.approx(40.5) and stats["p99_ms"] == pytest.approx(95.5)


def test_a_manual_reset_is_no_control_period_and_the_arm_starts_still():
    clock = FakeClock()
    env = twin(clock)
    td = env.reset()
    td = env.step(td.set("action", torch.full((6,), 0.2)))["next"].select("observation")
    clock.advance(5.0)  # a person resets the arm
    td = env.reset()
    before = float(env.backend.data.time)
    env.step(td.set("action", torch.zeros(6)))
    assert env.control_period_stats()["measured"] == 0  # the 5 s across the reset is not a period
    assert float(env.backend.data.time) - before == pytest.approx(PERIOD, abs=0.002)  # not 5 s of physics
    assert env.overruns == 0
    assert np.allclose(env.backend.read_state().qd, 0.0, atol=1e-4)  # at rest (servo jitter), not moving at 0.2


def test_a_hold_stops_the_arm_and_the_next_step_starts_a_fresh_period():
    """The trainer waiting at an episode boundary for its learner (learner.mode=async) holds the arm: 300 ms later
    the next step is no overrun and no 340 ms period, and the arm was stopped (its command zero)."""
    clock = FakeClock()
    env = twin(clock)
    td = env.reset()
    td = env.step(td.set("action", torch.full((6,), 0.3)))["next"].select("observation")
    env.hold()
    assert np.allclose(env.backend._cmd, 0.0)  # the speedj command the arm follows is zero
    clock.advance(0.300)
    env.step(td.set("action", torch.zeros(6)))
    assert env.overruns == 0 and env.control_period_stats()["measured"] == 0
    assert env.time_left() == pytest.approx(PERIOD)


def test_the_period_histogram_quantiles_by_hand():
    env = UR3Env("reacher")  # the histogram does not depend on the backend
    for seconds in [0.0402] * 98 + [0.1002] * 2:
        env._record_period(seconds)
    assert env.control_period_stats() == {"median_ms": pytest.approx(40.5), "p99_ms": pytest.approx(100.5),
                                          "measured": 100}
    env._record_period(2.0)  # beyond the histogram: the last bin, an infinite upper edge
    assert env.control_period_stats()["measured"] == 101


def test_on_the_real_clock_a_stalled_trainer_overruns_and_a_quick_one_does_not():
    env = UR3Env("reacher", backend="sim_realtime")
    assert env.backend.realtime
    td = env.reset()
    start = time.monotonic()
    for i in range(30):
        td = env.step(td.set("action", torch.zeros(6)))["next"].select("observation")
        td.set("action", torch.zeros(6))
        if i == 10:
            time.sleep(0.15)  # several periods: late however loaded the machine
    assert env.overruns >= 1
    assert time.monotonic() - start >= 29 * PERIOD  # paced: never faster than the period


def test_a_simulated_time_run_makes_every_update_algorithm_1_owes(tmp_path):
    """In simulated time nothing is skipped: each agent's updates (counted as they are made) equal its steps past
    heat-up (40), so updates_achieved is 1 for both; progress.csv carries the same fractions."""
    from torchrl_reset_recipes import train

    summary = train.train(quick_config(tmp_path))
    assert summary["updates_achieved"] == {"forward": 1.0, "reset": 1.0}
    assert summary["overruns"] == 0 and summary["control_period"] is None  # not a real-time arm
    import csv

    with open(tmp_path / "progress.csv", newline="") as f:
        last = list(csv.DictReader(f))[-1]
    assert float(last["forward_updates_achieved"]) == 1.0 and float(last["reset_updates_achieved"]) == 1.0


def joint0(env: UR3Env) -> float:
    return float(env.backend.read_state().q[0])


def test_a_late_trainer_leaves_the_arm_on_its_last_command_and_the_new_one_starts_when_sent():
    """1 s late: the arm ran at its last command (0.1 rad/s on joint 0) the whole second; the new command (stop)
    acts only from when it is sent. By hand (speedj ramps at 1.4 rad/s^2, 0.1 rad/s reached after 71 ms): over
    the late second 0.1 rad, then within the 40 ms period the ramp down from 0.1: 0.1 * 0.04 - 1.4 * 0.04^2 / 2
    = 2.9 mrad. Run under the new command, the second would have moved it 0.1^2 / (2 * 1.4) = 3.6 mrad in all."""
    clock = FakeClock()
    env = twin(clock)
    td = env.reset()
    for _ in range(5):  # 200 ms at 0.1 rad/s: the arm at the commanded speed
        td = env.step(td.set("action", torch.tensor([0.1, 0, 0, 0, 0, 0])))["next"].select("observation")
    before = joint0(env)
    clock.advance(1.0)
    env.step(td.set("action", torch.zeros(6)))
    assert env.overruns == 1
    assert joint0(env) - before == pytest.approx(0.1 + 0.0029, abs=0.002)


def test_after_a_hold_the_arm_rests_through_the_pause_and_the_next_command_acts_for_one_period():
    """Held for 5 s (the trainer waiting for its learner, idling now and then): the arm stops and stays; the next
    command (0.1 rad/s) then moves joint 0 by its ramp over one period, 1.4 * 0.04^2 / 2 = 1.1 mrad at most,
    not 5 s worth of it (0.5 rad)."""
    clock = FakeClock()
    env = twin(clock)
    td = env.reset()
    td = env.step(td.set("action", torch.tensor([0.3, 0, 0, 0, 0, 0])))["next"].select("observation")
    env.hold()
    sim_at_hold = float(env.backend.data.time)
    for _ in range(100):
        clock.advance(0.05)
        env.idle()
    at_rest = joint0(env)
    assert float(env.backend.data.time) - sim_at_hold == pytest.approx(5.0, abs=0.002)  # the pause, simulated
    assert np.allclose(env.backend.read_state().qd, 0.0, atol=1e-3)
    sim_before = float(env.backend.data.time)
    env.step(td.set("action", torch.tensor([0.1, 0, 0, 0, 0, 0])))
    assert float(env.backend.data.time) - sim_before == pytest.approx(PERIOD, abs=0.002)
    assert 0.0 < joint0(env) - at_rest <= 0.00112 + 1e-4
    assert env.overruns == 0 and env.time_left() == pytest.approx(PERIOD)


def test_a_waiting_actor_keeps_the_arm_up_to_date():
    """While the async actor waits for its learner, it brings the robot up to the present at each poll."""
    import queue
    import threading
    from types import SimpleNamespace

    from torchrl_reset_recipes.training.async_learner import AsyncLearner

    idles = []
    actor = object.__new__(AsyncLearner)
    actor.robot = SimpleNamespace(idle=lambda: idles.append(time.monotonic()))
    actor.outbox, actor.processed, actor.timeout = queue.Queue(), 0, 10.0
    actor.updates, actor.last_losses, actor._probe_callbacks = {}, {}, []
    actor.process = SimpleNamespace(is_alive=lambda: True)
    threading.Timer(0.5, actor.outbox.put, args=(("progress", 3, {}, {}),)).start()
    actor._wait_until(3, "a test")
    assert actor.processed == 3
    assert len(idles) >= 2  # polled every 50 ms for 0.5 s: about 10, a loaded machine fewer


def test_on_a_real_time_arm_the_run_holds_the_arm_before_each_evaluation_and_checkpoint():
    """Both take longer than a control period: the arm is held first (evaluations every 10 steps, checkpoints
    every 25: holds at 10, 20, 25 and 30, each just before what it covers, and nowhere else)."""
    from types import SimpleNamespace

    from torchrl_reset_recipes.training.single_run import TrainingRun

    events = []
    run = SimpleNamespace(
        cfg=SimpleNamespace(eval_every=10, log_every=1000, checkpoint_every=25),
        collector=SimpleNamespace(frames=0),
        record=SimpleNamespace(step=lambda batch, phase: None, evaluation=lambda result: None,
                               log=lambda learner, env: None),
        robot=SimpleNamespace(hold=lambda: events.append(("hold", run.collector.frames))),
        evaluation=lambda: events.append(("evaluation", run.collector.frames)),
        checkpoint=lambda: events.append(("checkpoint", run.collector.frames)),
        learner=None, env=None,
    )
    batch = torch.zeros(1)
    for _ in range(30):
        run.collector.frames += 1
        TrainingRun.after_step(run, batch, "forward")
    assert events == [("hold", 10), ("evaluation", 10), ("hold", 20), ("evaluation", 20), ("hold", 25),
                      ("checkpoint", 25), ("hold", 30), ("evaluation", 30)]


def test_only_a_real_time_arm_keeps_the_set_up_out_of_the_garbage_collector():
    import gc

    from torchrl_reset_recipes.training.single_run import set_up_frozen

    with set_up_frozen(None):
        assert gc.get_freeze_count() == 0
    with set_up_frozen(object()):
        assert gc.get_freeze_count() > 0
    assert gc.get_freeze_count() == 0
