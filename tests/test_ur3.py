"""The UR3 environment without a robot: the DH-built twin, speedj emulation, the stick, real-time pacing,
and the ur_rtde backend's safety logic against in-process fakes of ur_rtde's classes."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from torchrl_reset_envs import UR3Env, make_env
from torchrl_reset_envs.ur3 import PEG_TARGET, REACHER_GOAL, console_manual_reset
from torchrl_reset_envs.ur3_backends import RobotFault, RobotState, UR3Backend
from torchrl_reset_envs.ur3_rtde import ConnectionLost, RTDEBackend
from torchrl_reset_envs.ur3_model import HOME_Q, VELOCITY_LIMITS, build_ur3_spec, flange_pose

from fake_ur_rtde import FakeURController

W = math.atanh(math.sqrt(0.95))


# ---------------------------------------------------------------------------------------------- the model
def test_mujoco_twin_matches_the_dh_kinematics():
    import mujoco

    model = build_ur3_spec("peg").compile()
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    for _ in range(100):
        q = rng.uniform(-math.pi, math.pi, 6)
        data.qpos[:6] = q
        mujoco.mj_kinematics(model, data)
        p, rot = flange_pose(q)
        np.testing.assert_allclose(data.site("flange").xpos, p, atol=1e-9)
        np.testing.assert_allclose(data.site("flange").xmat.reshape(3, 3), rot, atol=1e-9)
    # the published zero-configuration flange position of the UR3, in the base frame (ur3.md section 3)
    np.testing.assert_allclose(flange_pose(np.zeros(6), world=False)[0], [-0.4569, -0.19425, 0.06655], atol=1e-9)


def test_home_points_the_flange_down_above_the_table():
    p, rot = flange_pose(HOME_Q)
    np.testing.assert_allclose(p, [0.3, -0.2, 0.4], atol=1e-3)
    assert rot[:, 2] @ np.array([0, 0, -1.0]) > math.cos(math.radians(0.1))


# ---------------------------------------------------------------------------------------------- sim backend
@pytest.mark.parametrize("task, obs_dim", [("peg", 12), ("reacher", 13)])
def test_sim_tasks_pass_specs_and_run_a_few_hundred_random_steps(task, obs_dim):
    env = make_env(f"ur3_{task}")
    check_env_specs(env)
    td = env.reset()
    assert td["observation"].shape == (obs_dim,) and td["reset_success"].item() and not td["irrecoverable"].item()
    rollout = env.rollout(300, break_when_any_done=False)
    rewards = rollout["next", "reward"]
    assert torch.isfinite(rollout["next", "observation"]).all() and 0 <= rewards.min() and rewards.max() <= 1
    assert not rollout["next", "terminated"].any()
    # cos^2 + sin^2 = 1 for every joint
    obs = rollout["next", "observation"]
    torch.testing.assert_close(obs[:, :6] ** 2 + obs[:, 6:12] ** 2, torch.ones(300, 6))


@pytest.mark.parametrize("task", ["peg", "reacher"])
def test_home_passes_the_at_initial_state_check_and_holding_still_stays_there(task):
    env = UR3Env(task)
    td = env.reset()
    assert td["reset_success"].item() and td["reset_reward"].item() == pytest.approx(1.0)
    for _ in range(100):  # 4 s without motion
        td = env.step(td.set("action", torch.zeros(6)))["next"]
        assert td["reset_success"].item() and not td["irrecoverable"].item()


def test_speedj_emulation_ramps_at_the_commanded_acceleration():
    env = UR3Env("peg", acceleration=1.4)
    td = env.reset()
    action = torch.zeros(6)
    action[0], action[1] = 0.3, 0.15
    q0 = env.backend.read_state().q
    for _ in range(25):  # 1 s
        td = env.step(td.set("action", action))["next"]
    state = env.backend.read_state()
    # the leading axis ramps to 0.3 rad/s in 0.3 / 1.4 = 0.214 s, then cruises:
    # displacement = 0.3 * (1 - 0.214 / 2) = 0.268 rad; the other axis, scaled, moves half as far
    assert state.q[0] - q0[0] == pytest.approx(0.3 * (1 - 0.3 / 1.4 / 2), abs=0.01)
    assert state.q[1] - q0[1] == pytest.approx(0.5 * (state.q[0] - q0[0]), abs=0.005)
    assert state.qd[0] == pytest.approx(0.3, abs=0.01) and state.qd[1] == pytest.approx(0.15, abs=0.01)
    assert np.abs(state.qd[2:]).max() < 0.01


def test_actions_are_bounded_by_the_speed_limit():
    env = UR3Env("peg", speed_limit=0.2)
    assert env.action_spec.space.high.max().item() == pytest.approx(0.2)
    td = env.reset()
    for _ in range(25):
        td = env.step(td.set("action", torch.full((6,), 3.0)))["next"]
    assert np.abs(env.backend.read_state().qd).max() < 0.2 + 0.01


def test_forced_tilt_spills_the_stick_and_the_flag_stays_until_a_manual_reset():
    env = UR3Env("reacher")
    td = env.reset()
    tilt = torch.zeros(6)
    tilt[4] = 0.3  # the wrist tilts the cup
    spilled_at = None
    for t in range(250):
        td = env.step(td.set("action", tilt))["next"]
        if td["irrecoverable"].item():
            spilled_at = t
            break
    assert spilled_at is not None and td["observation"][12].item() == 1.0 and not td["reset_success"].item()
    for _ in range(spilled_at + 50):  # tilt back past home: the stick stays spilled
        td = env.step(td.set("action", -tilt))["next"]
        assert td["irrecoverable"].item() and td["observation"][12].item() == 1.0 and not td["reset_success"].item()
        assert td["reset_reward"].item() == 0.0
    td = env.reset()  # the manual reset puts the stick back
    assert not td["irrecoverable"].item() and td["observation"][12].item() == 0.0 and td["reset_success"].item()


def test_forward_rewards_by_hand():
    env = UR3Env("peg")
    # at home the tip is 0.3 m below the flange at (0.3, -0.2, 0.1); the target is (0.3, 0, 0):
    # d = sqrt(0.2^2 + 0.1^2) = 0.2236, 0.2136 beyond the 0.01 tolerance, margin 0.2
    d = math.hypot(0.2, 0.1)
    assert np.linalg.norm(env.tip_position(HOME_Q) - PEG_TARGET) == pytest.approx(d, abs=1e-3)
    assert env.forward_reward(HOME_Q) == pytest.approx(1 - math.tanh(W * (d - 0.01) / 0.2) ** 2, abs=2e-3)
    reacher = UR3Env("reacher")
    # the flange starts 0.4 m from the goal: 0.38 beyond the 0.02 tolerance, margin 0.4
    assert np.linalg.norm(flange_pose(HOME_Q)[0] - REACHER_GOAL) == pytest.approx(0.4, abs=1e-9)
    assert reacher.forward_reward(HOME_Q) == pytest.approx(1 - math.tanh(W * 0.38 / 0.4) ** 2, abs=1e-6)


def test_bad_arguments_and_actions_get_clear_errors():
    with pytest.raises(ValueError, match="task must be"):
        UR3Env("juggler")
    with pytest.raises(ValueError, match="needs host"):
        UR3Env("peg", backend="rtde")
    with pytest.raises(ValueError, match="backend must be"):
        UR3Env("peg", backend="ros")
    env = UR3Env("peg")
    td = env.reset()
    with pytest.raises(ValueError, match=r"shape \(6,\)"):
        env.step(td.clone().set("action", torch.zeros(5)))
    with pytest.raises(ValueError, match="non-finite"):
        env.step(td.clone().set("action", torch.full((6,), float("nan"))))


# ---------------------------------------------------------------------------------------------- real time
class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t

    def sleep(self, dt):
        self.t += max(dt, 0.0)


class ClockedBackend(UR3Backend):
    """A still arm on a fake wall clock, recording commands."""

    realtime = True

    def __init__(self, clock):
        self.clock = clock
        self.commands = []
        self.protective = False

    def connect(self):
        pass

    def read_state(self):
        return RobotState(HOME_Q.copy(), np.zeros(6), self.clock(), protective_stop=self.protective,
                          halted=self.protective, reason="protective stop" if self.protective else None)

    def speedj(self, qd, acceleration):
        self.commands.append((self.clock(), np.array(qd)))
        return qd

    def stop(self):
        self.commands.append((self.clock(), "stop"))

    def move_home(self, q_home, speed):
        return True

    def close(self):
        pass

    def now(self):
        return self.clock()

    def wait_until(self, t):
        self.clock.sleep(t - self.clock())


def test_real_time_pacing_time_left_and_overruns():
    clock = FakeClock()
    backend = ClockedBackend(clock)
    env = UR3Env("peg", backend=backend, manual_reset=lambda env: None)
    td = env.reset()
    td = env.step(td.set("action", torch.zeros(6)))["next"]
    assert clock.t == pytest.approx(0.04) and env.time_left() == pytest.approx(0.04)
    clock.t += 0.03  # the trainer spends 30 ms: 10 ms left
    assert env.time_left() == pytest.approx(0.01)
    td = env.step(td.set("action", torch.zeros(6)))["next"]
    assert backend.commands[-1][0] == pytest.approx(0.07)  # sent at once
    assert clock.t == pytest.approx(0.08) and env.overruns == 0  # the 25 Hz grid is kept
    clock.t += 0.05  # 50 ms: the period was missed
    with pytest.warns(RuntimeWarning, match="overrun"):
        td = env.step(td.set("action", torch.zeros(6)))["next"]
    assert env.overruns == 1 and clock.t == pytest.approx(0.17)  # a full period from the late send


def test_protective_stop_ends_the_episode_and_stops_the_arm():
    clock = FakeClock()
    backend = ClockedBackend(clock)
    env = UR3Env("peg", backend=backend, manual_reset=lambda env: None)
    td = env.reset()
    backend.protective = True
    td = env.step(td.set("action", torch.zeros(6)))["next"]
    assert td["terminated"].item() and td["done"].item() and backend.commands[-1][1] == "stop"


# ---------------------------------------------------------------------------------------------- rtde backend, faithful fake
# The fake controller (tests/fake_ur_rtde.py) refuses commands as a UR controller does: during a
# protective stop (speedStop included), while its control script is stopped, on a robot that is not
# RUNNING; its unlock is refused for 5 s; its watchdog stops the script when not kicked.
@pytest.fixture
def rtde():
    clock = FakeClock()
    robot = FakeURController(clock)
    backend = RTDEBackend("robot", control_factory=robot.control, receive_factory=robot.receive,
                          dashboard_factory=robot.dashboard, clock=clock, sleep=clock.sleep)
    backend.connect()
    yield backend, robot, clock
    backend.close()


def test_rtde_arms_the_watchdog_and_kicks_it_with_every_command(rtde):
    backend, robot, clock = rtde
    assert robot.log[0][1:] == ("setWatchdog", True) and robot.watchdog_hz == backend.limits.watchdog_hz
    for _ in range(3):
        backend.speedj(np.zeros(6))
        backend.wait_until(clock.t + 0.04)
    assert robot.names()[1:] == ["speedJ", "kickWatchdog"] * 3
    # without commands the controller's watchdog stops the script after 1 / watchdog_hz (0.2 s) ...
    clock.t += 0.25
    state = backend.read_state()
    assert robot.watchdog_trips == 1 and state.halted and state.reason == "control script not running"
    assert not state.protective_stop
    # ... and recover() re-uploads it and re-arms the watchdog
    assert backend.recover() and robot.program_running and robot.watchdog_hz == backend.limits.watchdog_hz


def test_rtde_sends_the_filtered_command_and_never_more_than_the_cap(rtde):
    backend, robot, clock = rtde
    cap = 0.25 * VELOCITY_LIMITS  # (pi, pi, pi, 2pi, 2pi, 2pi) / 4
    sent = []
    for _ in range(60):  # 2.4 s of a 9 rad/s command: the arm ramps at a dt per period, up to the cap
        sent.append(backend.speedj(np.array([9.0, -9.0, 0.1, 9.0, -9.0, 0.0])))
        backend.wait_until(clock.t + 0.04)
    sent = np.array(sent)
    assert np.all(np.abs(sent) <= cap + 1e-12)
    assert np.all(np.abs(np.diff(sent, axis=0)) <= 1.4 * 0.04 + 1e-9)  # reachable in one period at a = 1.4
    speeds = [entry for entry in robot.log if entry[1] == "speedJ"]
    assert len(speeds) == 60 and np.abs(robot.qd).max() <= cap.max() + 1e-9


def test_rtde_refused_command_without_a_halt_and_an_exception_stop_the_arm(rtde, monkeypatch):
    backend, robot, clock = rtde
    control = backend.control
    monkeypatch.setattr(control, "speedJ", lambda *args: False)  # refused for no visible reason
    with pytest.raises(RobotFault, match="speedJ returned False"):
        backend.speedj(np.zeros(6))
    assert robot.names()[-1] == "speedStop"

    def broken(*args):
        raise OSError("socket closed")

    monkeypatch.setattr(control, "speedJ", broken)
    with pytest.raises(OSError):
        backend.speedj(np.zeros(6))
    assert robot.names()[-1] == "speedStop"


def test_rtde_close_stops_and_disconnects_once(rtde):
    backend, robot, clock = rtde
    backend.close()
    assert robot.names()[-3:] == ["speedStop", "stopScript", "disconnect"]
    n = len(robot.log)
    backend.close()
    assert len(robot.log) == n


def test_rtde_link_drop_and_stale_state_stop_the_arm(rtde):
    backend, robot, clock = rtde
    clock.t += 0.04
    backend.read_state()
    robot.stall()  # the receive side keeps returning the last values
    clock.t += 0.05
    backend.read_state()  # 50 ms without progress: still tolerated
    clock.t += 0.06
    with pytest.raises(ConnectionLost, match="not advanced"):
        backend.read_state()
    assert robot.names()[-1] == "speedStop"
    robot.stall(False)
    robot.connected = False
    with pytest.raises(ConnectionLost, match="lost the RTDE link"):
        backend.read_state()


def test_rtde_protective_stop_is_a_flag_and_stopping_is_best_effort(rtde):
    backend, robot, clock = rtde
    robot.protective_stop()
    clock.t += 0.04
    state = backend.read_state()
    assert state.protective_stop and state.halted and state.reason == "protective stop"
    # the controller refuses every command now, speedStop included: nothing raises, nothing is sent
    backend.stop()
    assert robot.log[-1][1:] == ("speedStop", False)
    assert np.all(backend.speedj(np.full(6, 0.1)) == 0.0) and robot.log[-1][1] == "speedStop"
    assert backend.protective_stops == 1


def test_rtde_emergency_stop_is_fatal(rtde):
    backend, robot, clock = rtde
    robot.safety_mode = 7  # robot emergency stop
    clock.t += 0.04
    with pytest.raises(RobotFault, match="emergency stop"):
        backend.read_state()


@pytest.mark.parametrize("mode, reason", [(5, "robot mode IDLE"), (3, "robot mode POWER_OFF")])
def test_rtde_a_robot_that_is_not_running_halts_the_episode(rtde, mode, reason):
    backend, robot, clock = rtde
    robot.robot_mode = mode
    clock.t += 0.04
    state = backend.read_state()
    assert state.halted and state.reason == reason and not state.protective_stop
    assert not backend.recover()  # software does not power the arm on: a person is asked


def test_rtde_too_many_protective_stops_is_fatal(rtde):
    backend, robot, clock = rtde
    with pytest.raises(RobotFault, match="protective stops within"):
        for _ in range(backend.limits.max_protective_stops + 1):
            robot.protective_stop()
            clock.t += 0.04
            backend.read_state()
            assert backend.recover()  # waits out the 5 s, unlocks, re-uploads


def test_rtde_recovery_waits_for_the_unlock_and_restarts_the_script(rtde):
    backend, robot, clock = rtde
    clock.t = 10.0
    robot.protective_stop()
    clock.t += 0.04
    backend.read_state()
    started = clock.t
    # an unlock right away is refused by the controller (ur_rtde raises)
    with pytest.raises(RuntimeError, match="until 5s after occurrence"):
        backend.dashboard.unlockProtectiveStop()
    assert backend.recover()
    unlocks = [(t, ok) for t, name, ok in robot.log if name == "unlockProtectiveStop"]
    assert unlocks[-1][1] and unlocks[-1][0] >= 10.0 + 5.0  # unlocked only once the controller accepts it
    assert robot.names()[-1] == "setWatchdog" and robot.program_running and robot.safety_mode == 1
    assert clock.t - started < 6.0
    # the next command goes through again
    backend.speedj(np.full(6, 0.02))
    assert robot.log[-1][1:] == ("kickWatchdog", True)


def test_ur3_env_on_the_rtde_backend_ends_the_episode_on_a_protective_stop_and_recovers(rtde):
    backend, robot, clock = rtde
    asked = []
    env = UR3Env("peg", backend=backend, manual_reset=lambda env: console_manual_reset(env, prompt=asked.append))
    td = env.reset()  # console manual reset: moves home (the fake arm arrives), no prompt needed
    assert td["reset_success"].item() and "moveJ" in robot.names()
    for _ in range(3):
        td = env.step(td.set("action", torch.full((6,), 0.05)))["next"]
    assert robot.names().count("speedJ") == 3 and env.overruns == 0
    robot.protective_stop()
    td = env.step(td.set("action", torch.zeros(6)))["next"]  # no exception: the episode ends with a flag
    assert td["terminated"].item() and td["done"].item()
    assert robot.log[-1][1:] == ("speedStop", False)  # best-effort stop, refused
    td = env.reset()  # the manual reset recovers the robot, moves home and training goes on
    assert asked == [] and td["reset_success"].item() and not td["done"].item()
    td = env.step(td.set("action", torch.full((6,), 0.05)))["next"]
    assert not td["terminated"].item() and robot.log[-1][1:] == ("kickWatchdog", True)
    assert env.safety_counters()["protective_stops"] == 1 and env.safety_counters()["halts"] == 1


def test_console_manual_reset_asks_a_person_only_when_recovery_or_the_move_fails(rtde):
    backend, robot, clock = rtde
    env = UR3Env("reacher", backend=backend, manual_reset=lambda env: None, home_speed=0.1)
    env.reset()
    # a robot left idle: software may not clear it, so the person is asked; then it still is idle
    robot.robot_mode = 5
    asked = []
    with pytest.raises(RuntimeError, match="still halted"):
        console_manual_reset(env, prompt=asked.append)
    assert "robot mode IDLE" in asked[0]
    # the person powers it on: the spilled stick and a failing move home still need them
    robot.robot_mode = 7
    env.spilled = True
    robot.q = HOME_Q + 0.3
    backend.home_timeout = 0.5  # a slow move that cannot arrive in time
    asked.clear()
    with pytest.raises(RuntimeError, match="did not reach home"):
        console_manual_reset(env, prompt=asked.append, attempts=2)
    assert "stick is spilled" in asked[0] and "could not reach home" in asked[1]
    backend.home_timeout = 30.0
    asked.clear()
    console_manual_reset(env, prompt=asked.append)
    assert "stick is spilled" in asked[0] and len(asked) == 1
    np.testing.assert_allclose(robot.q, HOME_Q, atol=backend.home_tolerance)


# ---------------------------------------------------------------------------------------------- rtde loopback
def test_rtde_receive_side_against_a_fake_rtde_server_in_another_process(tmp_path):
    """Real ur_rtde receive interface <-> a fake controller on a 127.0.0.x address (skipped without ur_rtde)."""
    import subprocess
    import sys
    import time
    from pathlib import Path

    rtde_receive = pytest.importorskip("rtde_receive")
    host = f"127.0.0.{np.random.default_rng().integers(2, 250)}"
    mode = tmp_path / "mode"
    mode.write_text("normal")
    server = subprocess.Popen([sys.executable, str(Path(__file__).parent / "rtde_fake_server.py"), host, str(mode)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert server.stdout.readline().strip() == "ready", server.stderr.read()
        variables = ["timestamp", "actual_q", "actual_qd", "robot_mode", "safety_mode", "safety_status_bits",
                     "robot_status_bits", "runtime_state"]
        robot = FakeURController(time.monotonic)  # the control and dashboard side
        backend = RTDEBackend(host, control_factory=robot.control, dashboard_factory=robot.dashboard,
                              receive_factory=lambda h: rtde_receive.RTDEReceiveInterface(h, 125.0, variables),
                              host_watchdog=False)
        backend.connect()
        time.sleep(0.1)
        state = backend.read_state()
        np.testing.assert_allclose(state.q, HOME_Q, atol=1e-12)
        assert not state.protective_stop

        def wait_for(condition, seconds=2.0):
            deadline = time.monotonic() + seconds
            while time.monotonic() < deadline:
                if condition():
                    return True
                time.sleep(0.02)
            return False

        mode.write_text("protective")
        assert wait_for(lambda: backend.read_state().protective_stop)
        mode.write_text("freeze")  # the link stays up, the data stops: ur_rtde repeats the last values
        with pytest.raises(ConnectionLost, match="not advanced"):
            wait_for(lambda: backend.read_state() is None)
        mode.write_text("normal")  # data flows again: readings recover
        time.sleep(0.3)
        assert not backend.read_state().protective_stop
        mode.write_text("exit")  # the controller drops the link
        with pytest.raises(ConnectionLost):
            wait_for(lambda: backend.read_state() is None)
        assert wait_for(lambda: not backend.receive.isConnected())
        with pytest.raises(ConnectionLost, match="lost the RTDE link"):
            backend.read_state()
    finally:
        server.kill()
        server.wait()


def test_sim_simulator_state_restores_the_exact_trajectory():
    env = UR3Env("reacher")
    td = env.reset()
    actions = torch.rand(40, 6) - 0.5
    for a in actions[:10]:
        td = env.step(td.set("action", a))["next"]
    state = env.get_simulator_state()

    def replay(start):
        t, out = start.clone(), []
        for a in actions[10:]:
            t = env.step(t.set("action", a))["next"]
            out.append(t["observation"])
        return torch.stack(out)

    first = replay(td)
    env.reset()
    env.set_simulator_state(state)
    torch.testing.assert_close(replay(td), first, rtol=0, atol=0)


def test_host_watchdog_that_cannot_stop_the_arm_never_feeds_the_controller_watchdog(rtde, monkeypatch):
    backend, robot, clock = rtde
    backend.speedj(np.full(6, 0.02))
    clock.t += 0.13  # past the host watchdog's 3 periods, before the controller's 0.2 s
    monkeypatch.setattr(backend.control, "speedStop", lambda a=10.0: False)  # the stop does not go through
    kicks = robot.names().count("kickWatchdog")
    assert not backend.check_watchdog() and not backend.check_watchdog()
    assert robot.names().count("kickWatchdog") == kicks and backend.watchdog_stops == 0
    clock.t += 0.1  # so the controller's own watchdog stops the control script, as it should
    assert backend.read_state().reason == "control script not running" and robot.watchdog_trips == 1
    monkeypatch.undo()
    assert backend.recover()
    # with a working stop, the host watchdog stops the arm once and then keeps the controller's watchdog fed
    backend.speedj(np.zeros(6))
    clock.t += 0.13
    assert backend.check_watchdog() and robot.log[-1][1:] == ("speedStop", True)
    for _ in range(30):  # 0.3 s more, checked every 10 ms as the watchdog thread does
        clock.t += 0.01
        assert not backend.check_watchdog() and robot.log[-1][1:] == ("kickWatchdog", True)
    assert backend.watchdog_stops == 1 and robot.program_running and robot.watchdog_trips == 1


def test_a_deliberate_hold_is_no_stall_the_watchdog_keeps_the_script_alive_through_it(rtde):
    """UR3Env.hold() (the trainer pausing for its learner, an evaluation, a checkpoint): the arm stopped by the
    trainer is not stopped again by the host watchdog nor counted as a stall; the controller's watchdog is fed, so
    after 2 s (ten times its 0.2 s) the script still runs and the next command goes through."""
    backend, robot, clock = rtde
    backend.speedj(np.full(6, 0.02))
    backend.stop()
    assert robot.log[-1][1:] == ("speedStop", True)
    for _ in range(200):  # 2 s of checks, every 10 ms as the watchdog thread does
        clock.t += 0.01
        assert not backend.check_watchdog()
    assert backend.watchdog_stops == 0 and robot.names().count("speedStop") == 1
    assert robot.watchdog_trips == 0 and robot.program_running
    assert not backend.read_state().halted
    backend.speedj(np.full(6, 0.02))
    assert robot.log[-2][1:] == ("speedJ", True)


def test_a_protective_stop_that_refuses_speedstop_is_logged_once_per_stretch_without_commands(rtde, caplog):
    """The watchdog thread checks every 10 ms; a protectively stopped controller refuses speedStop for the
    whole stop (5 s at least before an unlock): one error line, not 500. A new stretch after a command says it anew."""
    backend, robot, clock = rtde
    failures = lambda: sum("speedStop" in r.getMessage() for r in caplog.records)  # noqa: E731
    with caplog.at_level("DEBUG", logger="torchrl_reset_envs"):
        for stretch in (1, 2):
            backend.speedj(np.full(6, 0.02))
            robot.protective_stop()
            clock.t += 0.13  # past the host watchdog's 3 periods
            for _ in range(100):  # one second of checks, every 10 ms
                assert not backend.check_watchdog()
                clock.t += 0.01
            assert failures() == stretch
            clock.t += 5.0  # the controller's 5 s, then recovery as the manual reset does it
            assert backend.recover()


def test_the_move_home_is_not_taken_when_its_path_leaves_the_boxes(rtde):
    backend, robot, clock = rtde
    limits = backend.limits
    # a person left the arm outside the joint box on the elbow: a path home that goes no further out is fine
    start = HOME_Q.copy()
    start[2] = limits.joint_high[2] + 0.05
    assert backend.path_is_safe(start, HOME_Q)
    # a path that swings the shoulder beyond its box on the way is refused, and the arm does not move
    away = HOME_Q.copy()
    away[1] = limits.joint_low[1] + 0.01
    target = HOME_Q.copy()
    target[1] = limits.joint_high[1] + 0.2
    assert not backend.path_is_safe(away, target)
    robot.q = away.copy()
    clock.t += 0.04
    moves = robot.names().count("moveJ")
    assert not backend.move_home(target, speed=0.2) and robot.names().count("moveJ") == moves


def test_a_refusal_the_receive_side_explains_a_moment_later_ends_the_episode_not_the_run(rtde, monkeypatch):
    backend, robot, clock = rtde
    # the control side refuses first; the protective stop shows on the receive side 20 ms later
    def refuse_then_stop(*args):
        robot.protective_stop_at = clock.t + 0.02
        return False

    monkeypatch.setattr(backend.control, "speedJ", refuse_then_stop)
    real_sleep = backend._sleep

    def sleep(dt):
        real_sleep(dt)
        if clock.t >= getattr(robot, "protective_stop_at", np.inf):
            robot.protective_stop()

    monkeypatch.setattr(backend, "_sleep", sleep)
    assert np.all(backend.speedj(np.full(6, 0.02)) == 0.0)  # no exception
    assert backend.read_state().protective_stop and backend.refused_commands == 1
