"""The real arm's safety: the command filter's guarantees (property tests), closed loops in the twin,
the host watchdog, and a short training loop against the faithful fake of ur_rtde."""
from __future__ import annotations

import math
import time

import mujoco
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from tensordict.nn import TensorDictModule

from fake_ur_rtde import FakeURController
from torchrl_reset import DualCollector
from torchrl_reset_envs import UR3Env
from torchrl_reset_envs.ur3 import console_manual_reset
from torchrl_reset_envs.ur3_backends import SimBackend
from torchrl_reset_envs.ur3_rtde import RTDEBackend
from torchrl_reset_envs.ur3_model import HOME_Q, build_ur3_spec
from torchrl_reset_envs.ur3_safety import SafetyFilter, SafetyLimits, nearest_feasible

PERIOD = 0.04
ACC = 1.4
CAP = 0.25 * np.array([math.pi] * 3 + [2 * math.pi] * 3)  # a quarter of the UR3's joint speed limits
# the default horizon by hand: one period plus the time to brake from the largest cap at ACC
HORIZON = PERIOD + 0.25 * 2 * math.pi / ACC  # 1.162 s


class Kinematics:
    """Flange position and Jacobian from the MuJoCo twin (independent of the filter's DH code)."""

    def __init__(self):
        self.model = build_ur3_spec("peg").compile()
        self.data = mujoco.MjData(self.model)
        self.site = self.model.site("flange").id
        self.jacp = np.zeros((3, self.model.nv))

    def __call__(self, q):
        self.data.qpos[:6] = q
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_comPos(self.model, self.data)
        mujoco.mj_jacSite(self.model, self.data, self.jacp, None, self.site)
        return self.data.site_xpos[self.site].copy(), self.jacp[:, :6].copy()


KIN = Kinematics()


def test_the_horizon_and_the_cap_are_the_documented_ones():
    limits = SafetyLimits()
    np.testing.assert_allclose(limits.cap, CAP, rtol=0, atol=1e-15)
    assert limits.horizon_for(PERIOD) == pytest.approx(HORIZON, rel=1e-12)
    np.testing.assert_allclose(CAP, [0.7854, 0.7854, 0.7854, 1.5708, 1.5708, 1.5708], atol=1e-4)


def violations(q, w, v, limits, tol=1e-7):
    """The constraints the filter promises (ur3_safety's docstring), checked with MuJoCo's kinematics."""
    found = []
    if np.any(np.abs(v) > CAP + tol):
        found.append("cap")
    if np.any(np.abs(v - w) > ACC * PERIOD + tol):
        found.append("one-period reach")
    for j in range(6):
        high = limits.joint_high[j] - limits.joint_margin - q[j]
        low = limits.joint_low[j] + limits.joint_margin - q[j]
        if v[j] * HORIZON > max(high, 0.0) + tol * HORIZON or v[j] * HORIZON < min(low, 0.0) - tol * HORIZON:
            found.append(f"joint {j}")
    p, jac = KIN(q)
    motion = jac @ v * HORIZON
    for k in range(3):
        high = limits.cartesian_high[k] - limits.cartesian_margin - p[k]
        low = limits.cartesian_low[k] + limits.cartesian_margin - p[k]
        if motion[k] > max(high, 0.0) + 1e-6 or motion[k] < min(low, 0.0) - 1e-6:
            found.append(f"cartesian {k}")
    nxt, _ = KIN(q + v * PERIOD)
    out_high = (nxt > limits.cartesian_high + 1e-9) & (nxt > p + 1e-9)
    out_low = (nxt < limits.cartesian_low - 1e-9) & (nxt < p - 1e-9)
    if np.any(out_high | out_low):
        found.append("true flange one period ahead")
    return found


# where a box face lies from the current pose: beyond it (< 0), on it, within the margin, near, far
FACE = st.sampled_from([-0.02, 0.0, 0.004, 0.011, 0.03, 0.1, 0.4, 3.0])


@st.composite
def situations(draw):
    q = HOME_Q + np.array(draw(st.lists(st.floats(-1.2, 1.2), min_size=6, max_size=6)))
    speed_scale = draw(st.sampled_from([0.0, 0.02, 0.3, 1.0]))
    w = np.array(draw(st.lists(st.floats(-1, 1), min_size=6, max_size=6))) * CAP * speed_scale
    joint_low = q - np.array(draw(st.lists(FACE, min_size=6, max_size=6)))
    joint_high = q + np.array(draw(st.lists(FACE, min_size=6, max_size=6)))
    p, _ = KIN(q)
    cart_low = p - np.array(draw(st.lists(FACE, min_size=3, max_size=3)))
    cart_high = p + np.array(draw(st.lists(FACE, min_size=3, max_size=3)))
    # a box must be a box with room for its margins: widen a degenerate one on its far side
    joint_high = np.maximum(joint_high, joint_low + 0.05)
    cart_high = np.maximum(cart_high, cart_low + 0.05)
    limits = SafetyLimits(joint_low=joint_low, joint_high=joint_high, cartesian_low=cart_low, cartesian_high=cart_high)
    kind = draw(st.sampled_from(["wild", "wild", "near the motion"]))
    if kind == "wild":  # anything up to 10 rad/s
        u = np.array(draw(st.lists(st.floats(-10, 10), min_size=6, max_size=6)))
    else:
        u = w + np.array(draw(st.lists(st.floats(-0.5, 0.5), min_size=6, max_size=6))) * ACC * PERIOD
    return q, w, u, limits


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(situations())
def test_the_filtered_command_meets_every_constraint_or_is_zero(situation):
    q, w, u, limits = situation
    safety = SafetyFilter(limits, PERIOD)
    v = safety(q, u, w)
    if safety.fallbacks:
        assert np.all(v == 0.0)  # zero velocity: the arm brakes at the fixed acceleration
    else:
        assert violations(q, w, v, limits) == []


@st.composite
def safe_situations(draw):
    """Commands that are safe with room to spare: faces far away, a command near the current motion."""
    q = HOME_Q + np.array(draw(st.lists(st.floats(-0.3, 0.3), min_size=6, max_size=6)))
    w = np.array(draw(st.lists(st.floats(-0.3, 0.3), min_size=6, max_size=6))) * CAP
    far = st.sampled_from([1.0, 3.0])
    joint_low = q - np.array(draw(st.lists(far, min_size=6, max_size=6)))
    joint_high = q + np.array(draw(st.lists(far, min_size=6, max_size=6)))
    p, _ = KIN(q)
    cart_low = p - np.array(draw(st.lists(far, min_size=3, max_size=3)))
    cart_high = p + np.array(draw(st.lists(far, min_size=3, max_size=3)))
    limits = SafetyLimits(joint_low=joint_low, joint_high=joint_high, cartesian_low=cart_low, cartesian_high=cart_high)
    u = w + np.array(draw(st.lists(st.floats(-0.9, 0.9), min_size=6, max_size=6))) * ACC * PERIOD
    return q, w, u, limits


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(safe_situations())
def test_a_safe_command_passes_unchanged_bit_for_bit(situation):
    q, w, u, limits = situation
    assume(violations(q, w, u, limits, tol=-1e-6) == [])  # the test's own check, with MuJoCo's kinematics
    safety = SafetyFilter(limits, PERIOD)
    assert np.array_equal(safety(q, u, w), u) and safety.changed == 0


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(situations())
def test_a_safe_command_passes_unchanged(situation):
    q, w, u, limits = situation
    safety = SafetyFilter(limits, PERIOD)
    if violations(q, w, u, limits, tol=-1e-6) == []:  # safe with room to spare: must not be touched
        assert np.array_equal(safety(q, u, w), u)
    v = safety(q, u, w)
    if not safety.fallbacks:  # what the filter returns is safe, so it passes again unchanged
        assert np.array_equal(safety(q, v, w), v)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(situations())
def test_the_filtered_command_is_the_nearest_safe_one(situation):
    # against scipy's SLSQP on the same constraint set: the active-set solution is at least as near
    from scipy.optimize import minimize

    q, w, u, limits = situation
    safety = SafetyFilter(limits, PERIOD)
    v = safety(q, u, w)
    if safety.fallbacks:
        return
    G, h = safety.constraints(q, w)
    result = minimize(lambda x: 0.5 * np.sum((x - u) ** 2), v, jac=lambda x: x - u, method="SLSQP",
                      constraints=[{"type": "ineq", "fun": lambda x: h - G @ x, "jac": lambda x: -G}],
                      options={"ftol": 1e-14, "maxiter": 500})
    if result.success and np.all(G @ result.x <= h + 1e-9):
        assert np.sum((v - u) ** 2) <= np.sum((result.x - u) ** 2) + 1e-9


def test_the_active_set_solver_on_degenerate_starts():
    # x <= 1 three times (scaled), y <= 1, x + y <= 2: all five active at the start (1, 1), rank 2
    G = np.array([[1.0, 0], [2, 0], [0.5, 0], [0, 1], [1, 1]])
    h = np.array([1.0, 2, 0.5, 1, 2])
    for u, nearest in (((3.0, 0.5), (1.0, 0.5)), ((0.0, 5.0), (0.0, 1.0)), ((4.0, 4.0), (1.0, 1.0))):
        x, optimal = nearest_feasible(np.array(u), G, h, np.array([1.0, 1.0]))
        assert optimal
        np.testing.assert_allclose(x, nearest, atol=1e-12)
    # in 6 dimensions: the box |v_j| <= 1 plus the sum <= 1 and its duplicates, start at a vertex where
    # seven constraints meet; the nearest point to (2, ..., 2) is (1/6, ..., 1/6)
    eye = np.eye(6)
    G6 = np.vstack([eye, -eye, np.ones((3, 6)) * np.array([[1.0], [2.0], [0.5]])])
    h6 = np.concatenate([np.ones(12), [1.0, 2.0, 0.5]])
    start = np.array([1.0, -1, 1, -1, 1, -1.0])
    x, optimal = nearest_feasible(np.full(6, 2.0), G6, h6, start)
    assert optimal
    np.testing.assert_allclose(x, np.full(6, 1 / 6), atol=1e-10)


def test_the_active_set_solver_by_hand():
    # the nearest point of the half-plane x + y <= 1 (and the box |x|, |y| <= 2) to (2, 2) is (0.5, 0.5)
    G = np.array([[1.0, 1.0], [1, 0], [0, 1], [-1, 0], [0, -1]])
    h = np.array([1.0, 2, 2, 2, 2])
    x, _ = nearest_feasible(np.array([2.0, 2.0]), G, h, np.zeros(2))
    np.testing.assert_allclose(x, [0.5, 0.5], atol=1e-12)
    # a corner: with y <= 0.2 as well, the nearest point to (2, 2) is (0.8, 0.2)
    x, _ = nearest_feasible(np.array([2.0, 2.0]), np.vstack([G, [0, 1]]), np.append(h, 0.2), np.zeros(2))
    np.testing.assert_allclose(x, [0.8, 0.2], atol=1e-12)
    # a feasible target is returned as it is
    x, _ = nearest_feasible(np.array([0.3, -1.0]), G, h, np.zeros(2))
    np.testing.assert_allclose(x, [0.3, -1.0], atol=1e-15)


def test_bad_limits_and_inputs_get_clear_errors():
    with pytest.raises(ValueError, match="speed_fraction"):
        SafetyLimits(speed_fraction=1.5)
    with pytest.raises(ValueError, match="low bound"):
        SafetyLimits(cartesian_low=np.ones(3), cartesian_high=np.zeros(3))
    with pytest.raises(ValueError, match="cartesian_margin"):
        SafetyLimits(cartesian_margin=0.5)
    with pytest.raises(ValueError, match="6 entries"):
        SafetyFilter(SafetyLimits(), PERIOD)(HOME_Q, np.zeros(5))
    with pytest.raises(ValueError, match="non-finite"):
        SafetyFilter(SafetyLimits(), PERIOD)(HOME_Q, np.full(6, np.nan))
    with pytest.raises(ValueError, match="host watchdog"):
        RTDEBackend("robot", limits=SafetyLimits(watchdog_hz=10.0, host_watchdog_periods=3))


# ---------------------------------------------------------------------------------------------- closed loops
def closed_loop(mode: str, seed: int, steps: int, acceleration: float = ACC) -> dict:
    """The twin under filtered commands: adversarial (up to 10 rad/s, random or bang-bang) or drifting
    (0.5 rad/s in a direction that changes every 8 s, pushing into faces and corners), sent with
    ``acceleration``."""
    limits = SafetyLimits()
    backend = SimBackend("peg", limits=limits, period=PERIOD)
    backend.connect()
    rng = np.random.default_rng(seed)
    exits = {"joint": 0, "cartesian": 0, "cap": 0}
    worst = {"joint": -np.inf, "cartesian": -np.inf, "speed": 0.0}
    t, drift = 0.0, None
    for k in range(steps):
        if mode == "adversarial":
            u = rng.uniform(-10, 10, 6) if rng.random() < 0.5 else np.sign(rng.normal(size=6)) * 10
        else:
            if k % 200 == 0:
                drift = rng.normal(size=6)
                drift /= np.linalg.norm(drift)
            u = 0.5 * drift + rng.normal(scale=0.05, size=6)
        sent = backend.speedj(u, acceleration)
        exits["cap"] += int(np.any(np.abs(sent) > CAP + 1e-12))
        t += PERIOD
        backend.wait_until(t)
        state = backend.read_state()
        p, _ = KIN(state.q)
        joint_excess = np.max(np.maximum(state.q - limits.joint_high, limits.joint_low - state.q))
        cart_excess = np.max(np.maximum(p - limits.cartesian_high, limits.cartesian_low - p))
        exits["joint"] += int(joint_excess > 0)
        exits["cartesian"] += int(cart_excess > 0)
        worst["joint"] = max(worst["joint"], joint_excess)
        worst["cartesian"] = max(worst["cartesian"], cart_excess)
        worst["speed"] = max(worst["speed"], float(np.max(np.abs(state.qd) / CAP)))
    return {"exits": exits, "worst": worst, **backend.counters()}


@pytest.mark.parametrize("mode, seed, acceleration, max_fallbacks", [
    ("adversarial", 0, ACC, 0.05), ("drifting", 0, ACC, 0.25), ("drifting", 1, ACC, 0.25),
    ("drifting", 2, 0.2, 0.25),  # a gentler speedj: the filter plans its braking with it
])
def test_closed_loops_in_the_twin_never_leave_the_boxes_nor_exceed_the_cap(mode, seed, acceleration, max_fallbacks):
    result = closed_loop(mode, seed, 2500, acceleration)  # 100 s of arm time each
    print(f"\n{mode} seed {seed} a={acceleration}: {result}")
    assert result["exits"] == {"joint": 0, "cartesian": 0, "cap": 0}
    assert result["worst"]["joint"] < 0 and result["worst"]["cartesian"] < 0
    assert result["worst"]["speed"] < 1.02  # measured speeds: the cap plus the servos' tracking error
    assert result["filtered_commands"] == 2500
    # braking fallbacks happen where the Jacobian turns a motion along a face outwards; they stay rare
    assert result["filter_fallbacks"] <= max_fallbacks * 2500


def test_with_perfect_tracking_and_a_joint_box_only_the_braking_invariant_needs_no_fallback():
    # speedj's ramp integrated exactly (leading axis at a, the others scaled): the joint-box constraints
    # are an invariant, so the braking command is always feasible and no command falls back to zero
    limits = SafetyLimits(cartesian_low=np.full(3, -10.0), cartesian_high=np.full(3, 10.0))
    rng = np.random.default_rng(0)
    for acceleration in (ACC, 0.2):
        safety = SafetyFilter(limits, PERIOD)
        q, w, worst, drift = HOME_Q.copy(), np.zeros(6), -np.inf, None
        for k in range(2000):
            if k % 200 == 0:
                drift = rng.normal(size=6)
                drift /= np.linalg.norm(drift)
            u = 0.5 * drift + rng.normal(scale=0.05, size=6) if k % 2 else rng.uniform(-10, 10, 6)
            v = safety(q, u, w, acceleration)
            for _ in range(20):  # 2 ms steps
                dv = v - w
                lead = np.max(np.abs(dv))
                if lead > acceleration * 0.002:
                    dv *= acceleration * 0.002 / lead
                w = w + dv
                q = q + w * 0.002
            worst = max(worst, np.max(np.maximum(q - limits.joint_high, limits.joint_low - q)))
        assert safety.fallbacks == 0 and worst < -limits.joint_margin / 2


# ---------------------------------------------------------------------------------------------- host watchdog
def test_a_stall_between_steps_gets_a_speed_stop_from_the_host_watchdog_in_time():
    robot = FakeURController(time.monotonic)
    backend = RTDEBackend("robot", control_factory=robot.control, receive_factory=robot.receive,
                          dashboard_factory=robot.dashboard)  # real clock: the watchdog thread runs
    env = UR3Env("peg", backend=backend, manual_reset=lambda env: None)
    try:
        td = env.reset()
        for _ in range(3):
            td = env.step(td.set("action", torch.full((6,), 0.05)))["next"]
        last = robot.log[-1][0]
        time.sleep(0.5)  # the trainer stalls: an overrunning update, a checkpoint...
        stops = [t for t, name, ok in robot.log if name == "speedStop" and ok and t > last]
        timeout = backend.watchdog_timeout()
        assert timeout == pytest.approx(3 * 0.04)
        assert len(stops) == 1 and timeout <= stops[0] - last < timeout + 0.06
        assert robot.watchdog_trips == 0 and robot.program_running  # the host kept the controller's watchdog fed
        with pytest.warns(RuntimeWarning, match="overrun"):
            td = env.step(td.set("action", torch.full((6,), 0.05)))["next"]  # resumes normally
        assert not td["terminated"].item() and robot.log[-1][1:] == ("kickWatchdog", True)
        assert env.safety_counters()["watchdog_stops"] == 1
    finally:
        env.close()


# ---------------------------------------------------------------------------------------------- the loop
def joint_angles(observation: torch.Tensor) -> torch.Tensor:
    return torch.atan2(observation[..., 6:12], observation[..., :6])


def test_a_short_dual_collector_loop_survives_protective_stops_against_the_fake_controller():
    clock_time = [0.0]

    def clock():
        return clock_time[0]

    def sleep(dt):
        clock_time[0] += max(dt, 0.0)

    # the cell's controller has a tighter safety box than ours (a misconfigured cell): moving the
    # base a few hundredths of a radian takes the flange out of it, and the controller stops the arm
    from torchrl_reset_envs.ur3_model import flange_pose

    home = flange_pose(HOME_Q)[0]
    robot = FakeURController(clock, pstop_box=(home - 0.03, home + 0.03))
    backend = RTDEBackend("robot", control_factory=robot.control, receive_factory=robot.receive,
                          dashboard_factory=robot.dashboard, clock=clock, sleep=sleep)
    asked = []
    env = UR3Env("peg", backend=backend, manual_reset=lambda env: console_manual_reset(env, prompt=asked.append))
    home_q = torch.as_tensor(HOME_Q, dtype=torch.float32)
    calls = [0]

    def outwards(obs):
        calls[0] += 1
        if calls[0] == 20:  # once in a forward episode: a person walks into the cell (a light curtain)
            robot.protective_stop()
        return torch.tensor([0.4, 0, 0, 0, 0, 0.0]).expand(*obs.shape[:-1], 6)

    away = TensorDictModule(outwards, in_keys=["observation"], out_keys=["action"])
    back = TensorDictModule(lambda obs: (-2.0 * (joint_angles(obs) - home_q)).clamp(-0.5, 0.5),
                            in_keys=["observation"], out_keys=["action"])
    collector = DualCollector(env, away, back, max_forward_steps=15, max_reset_steps=40, total_frames=120)
    events = []
    try:
        steps = 0
        # a protective stop ends its episode (a termination): the collector says so, once
        with pytest.warns(UserWarning, match="UR3Env terminated an episode by itself") as warned:
            for batch in collector:
                steps += batch.numel()
                events += collector.pop_events()
    finally:
        collector.shutdown()
    assert sum("terminated an episode by itself" in str(w.message) for w in warned) == 1
    halted_in = {event["phase"] for event in events if event["outcome"] == "terminated"}
    assert halted_in == {"forward", "reset"}
    c = collector.counters
    assert steps == 120 and asked == []  # every stop was recovered without a person
    # the controller stopped the arm in forward and in reset episodes; each ended its episode
    assert c["terminations"] >= 2 and robot.protective_stops == c["terminations"]
    assert c["forward_episodes"] >= 2 and c["reset_episodes"] >= 2
    assert env.safety_counters()["protective_stops"] == robot.protective_stops
    assert env.safety_counters()["halts"] == c["terminations"]
