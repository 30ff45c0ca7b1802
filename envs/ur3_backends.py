"""How :class:`UR3Env` talks to an arm: one small interface, a MuJoCo twin and the real arm through ur_rtde.

Both backends speak joint angles (rad), joint velocities (rad/s) and a ``speedj`` command: "move
every joint at these velocities, reaching them with a bounded acceleration, until told otherwise".
"""
from __future__ import annotations

import abc
import atexit
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import mujoco
import numpy as np
import torch

from ._mujoco import get_physics, set_physics
from .ur3_model import HOME_Q, JOINT_HIGH, JOINT_LOW, VELOCITY_LIMITS, build_ur3_spec, flange_pose

__all__ = [
    "RobotState", "UR3Backend", "SimBackend", "RTDEBackend", "SafetyLimits", "RobotFault", "ConnectionLost",
    "SAFETY_PROTECTIVE_STOP_BIT", "SAFETY_FATAL_BITS", "filter_command", "cup_axis_tilt",
]

log = logging.getLogger("torchrl_reset_envs.ur3")

# RTDE safety_status_bits (UR RTDE guide): 0 normal, 1 reduced, 2 protective stopped, 3 recovery mode,
# 4 safeguard stopped, 5 system emergency stopped, 6 robot emergency stopped, 7 emergency stopped,
# 8 violation, 9 fault, 10 stopped due to safety
SAFETY_PROTECTIVE_STOP_BIT = 2
SAFETY_FATAL_BITS = (5, 6, 7, 8, 9)


class RobotFault(RuntimeError):
    """The arm is in a state where nothing may move (emergency stop, safety violation, fault, failed command)."""


class ConnectionLost(RobotFault):
    """The link to the controller dropped or its state stopped advancing."""


@dataclass
class RobotState:
    """One reading of the arm."""

    q: np.ndarray
    qd: np.ndarray
    timestamp: float
    protective_stop: bool = False
    extra: dict = field(default_factory=dict)


class UR3Backend(abc.ABC):
    """The operations :class:`UR3Env` needs from an arm."""

    #: whether time passes by itself (the real arm) or only through :meth:`wait_until` (a simulation)
    realtime: bool = False

    @abc.abstractmethod
    def connect(self) -> None: ...

    @abc.abstractmethod
    def read_state(self) -> RobotState: ...

    @abc.abstractmethod
    def speedj(self, qd: np.ndarray, acceleration: float) -> np.ndarray:
        """Command joint velocities; returns the velocities actually commanded (after safety filtering)."""

    @abc.abstractmethod
    def stop(self) -> None: ...

    @abc.abstractmethod
    def move_home(self, q_home: np.ndarray, speed: float) -> bool:
        """Move to ``q_home``; True when the arm ended within tolerance of it."""

    @abc.abstractmethod
    def close(self) -> None: ...

    @abc.abstractmethod
    def now(self) -> float:
        """The backend's clock (s)."""

    @abc.abstractmethod
    def wait_until(self, t: float) -> None:
        """Let the arm run until ``now() >= t``."""


# ---------------------------------------------------------------------------------------------- sim
class SimBackend(UR3Backend):
    """The MuJoCo twin (see :mod:`ur3_model`), with ``speedj`` emulated.

    A velocity reference follows the commanded velocities with the leading axis accelerating at
    ``acceleration`` and the others scaled to arrive at the same time (URScript ``speedj``); its
    integral drives stiff position servos. Physics runs at 2 ms steps. ``restore_home`` is the
    simulated manual reset: the arm at ``q_home``, at rest, the stick back upright in its cup.
    """

    realtime = False

    def __init__(self, task: str = "peg", *, timestep: float = 0.002, kp: float = 5000.0):
        self.task = task
        self.timestep = timestep
        self.kp = kp
        self.model = None
        self.data = None

    def connect(self) -> None:
        if self.model is not None:
            return
        spec = build_ur3_spec(self.task, kp=self.kp)
        spec.option.timestep = self.timestep
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self._arm_q = np.arange(6)  # the arm's joints come first in qpos/qvel
        self._cmd = np.zeros(6)
        self._acc = 1.0
        self._v_ref = np.zeros(6)
        self.restore_home(HOME_Q)

    def get_simulator_state(self) -> dict:
        """Physics plus the emulated speedj state (command, reference velocity, acceleration)."""
        return {"physics": get_physics(self.model, self.data), "v_ref": torch.from_numpy(self._v_ref.copy()),
                "cmd": torch.from_numpy(self._cmd.copy()), "acc": self._acc}

    def set_simulator_state(self, state: dict) -> None:
        set_physics(self.model, self.data, state["physics"], type(self).__name__)
        self._v_ref = state["v_ref"].numpy().copy()
        self._cmd = state["cmd"].numpy().copy()
        self._acc = float(state["acc"])

    def restore_home(self, q_home: np.ndarray) -> None:
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self._arm_q] = q_home
        self.data.ctrl[:] = q_home
        mujoco.mj_forward(self.model, self.data)
        self._cmd[:] = 0.0
        self._v_ref[:] = 0.0
        if self.task == "reacher":
            # let the stick settle in its cup with the arm held still
            mujoco.mj_step(self.model, self.data, nstep=250)
            self.data.qvel[self._arm_q] = 0.0

    def read_state(self) -> RobotState:
        extra = {}
        if self.task == "reacher":
            extra["stick_tilt"], extra["stick_offset"] = self.stick_geometry()
        return RobotState(self.data.qpos[self._arm_q].copy(), self.data.qvel[self._arm_q].copy(), float(self.data.time),
                          extra=extra)

    def stick_geometry(self) -> tuple[float, float]:
        """Angle (rad) between the stick and the cup's axis, and the stick base's distance from the cup's axis (m)."""
        cup = self.data.site("cup_centre")
        base, top = self.data.site("stick_base").xpos, self.data.site("stick_top").xpos
        axis = cup.xmat.reshape(3, 3)[:, 2]
        stick = (top - base) / max(np.linalg.norm(top - base), 1e-12)
        tilt = math.acos(float(np.clip(stick @ axis, -1.0, 1.0)))
        rel = base - cup.xpos
        offset = float(np.linalg.norm(rel - (rel @ axis) * axis))
        return tilt, offset

    def speedj(self, qd: np.ndarray, acceleration: float) -> np.ndarray:
        self._cmd = np.clip(np.asarray(qd, dtype=np.float64), -VELOCITY_LIMITS, VELOCITY_LIMITS)
        self._acc = float(acceleration)
        return self._cmd.copy()

    def stop(self) -> None:
        self._cmd = np.zeros(6)

    def move_home(self, q_home: np.ndarray, speed: float) -> bool:
        self.restore_home(q_home)
        return True

    def close(self) -> None:
        self.model = self.data = None

    def now(self) -> float:
        return float(self.data.time)

    def wait_until(self, t: float) -> None:
        steps = max(0, int(round((t - self.data.time) / self.model.opt.timestep)))
        dt = self.model.opt.timestep
        for _ in range(steps):
            dv = self._cmd - self._v_ref
            lead = float(np.max(np.abs(dv)))
            if lead > self._acc * dt:
                dv *= self._acc * dt / lead
            self._v_ref += dv
            self.data.ctrl[:] = np.clip(self.data.ctrl + self._v_ref * dt, JOINT_LOW, JOINT_HIGH)
            mujoco.mj_step(self.model, self.data)


# ---------------------------------------------------------------------------------------------- real arm
@dataclass
class SafetyLimits:
    """What the real backend enforces on every command (ur3.md section 6).

    Attributes:
        speed_fraction: commanded joint speeds are clipped to this fraction of the hardware limits.
        acceleration: the fixed ``speedj`` acceleration (rad/s^2 of the leading axis), at most 40.
        joint_low, joint_high: a joint-angle box (rad); a command that would leave it within one
            period has its outward components zeroed.
        cartesian_low, cartesian_high: a box (m, world frame) for the flange; a command that would
            take the flange out has its outward Cartesian component removed.
        watchdog_hz: the controller stops the arm when commands come slower than this.
        stale_after: the state counts as stale when the robot timestamp has not advanced for this long (s).
        max_protective_stops, protective_stop_window: more stops than this within the window (s) is fatal.
    """

    speed_fraction: float = 0.25
    acceleration: float = 1.4
    joint_low: np.ndarray = field(default_factory=lambda: HOME_Q - 1.5)
    joint_high: np.ndarray = field(default_factory=lambda: HOME_Q + 1.5)
    cartesian_low: np.ndarray = field(default_factory=lambda: np.array([0.05, -0.45, 0.30]))
    cartesian_high: np.ndarray = field(default_factory=lambda: np.array([0.55, 0.45, 0.75]))
    watchdog_hz: float = 10.0
    stale_after: float = 0.1
    max_protective_stops: int = 10
    protective_stop_window: float = 600.0

    def __post_init__(self):
        if not 0.0 < self.speed_fraction <= 1.0:
            raise ValueError(f"speed_fraction must lie in (0, 1], got {self.speed_fraction}.")
        if not 0.0 < self.acceleration <= 40.0:
            raise ValueError(f"acceleration must lie in (0, 40] rad/s^2 (ur_rtde's range), got {self.acceleration}.")
        for name in ("joint_low", "joint_high", "cartesian_low", "cartesian_high"):
            setattr(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        if np.any(self.joint_low >= self.joint_high) or np.any(self.cartesian_low >= self.cartesian_high):
            raise ValueError("each low bound must lie below its high bound.")


def _flange_jacobian(q: np.ndarray) -> np.ndarray:
    """3x6 Jacobian of the world flange position (finite differences of the DH model)."""
    p0 = flange_pose(q)[0]
    return np.stack([(flange_pose(q + dq)[0] - p0) / 1e-6 for dq in np.eye(6) * 1e-6], axis=1)


def filter_command(q: np.ndarray, qd: np.ndarray, dt: float, limits: SafetyLimits) -> np.ndarray:
    """The velocity command made safe: clipped, kept inside the joint box and the Cartesian box for ``dt``."""
    qd = np.clip(np.asarray(qd, dtype=np.float64), -limits.speed_fraction * VELOCITY_LIMITS,
                 limits.speed_fraction * VELOCITY_LIMITS)
    # Cartesian box: remove the outward Cartesian velocity along every axis the predicted flange would
    # leave the box by (through the Jacobian's pseudo-inverse, so the other axes keep their motion)
    jac = _flange_jacobian(q)
    jac_pinv = np.linalg.pinv(jac)
    for _ in range(3):
        p_next = flange_pose(q + qd * dt)[0]
        velocity = jac @ qd
        outward = ((p_next > limits.cartesian_high) & (velocity > 0)) | ((p_next < limits.cartesian_low) & (velocity < 0))
        if not outward.any():
            break
        qd = qd - jac_pinv @ np.where(outward, velocity, 0.0)
    # joint box: zero the components that would leave it
    q_next = q + qd * dt
    leaving = ((q_next > limits.joint_high) & (qd > 0)) | ((q_next < limits.joint_low) & (qd < 0))
    qd = np.where(leaving, 0.0, qd)
    return qd


class RTDEBackend(UR3Backend):
    """The real UR3 through ur_rtde (``pip install "torchrl-reset[robot]"``), with the safety features of ur3.md section 6.

    - every command is clipped and kept inside a joint box and a Cartesian box (:func:`filter_command`);
    - the controller's watchdog is armed on connection and kicked with every command, so the arm stops
      if this process stalls or dies;
    - every step checks the link (``isConnected``), that the robot timestamp advances, and the safety
      bits: a protective stop ends the episode (``RobotState.protective_stop``), too many of them, an
      emergency stop, a violation or a fault raise :class:`RobotFault`;
    - every command's boolean result is checked; ``speedStop`` is sent on any error, on :meth:`close`
      and at interpreter exit; :meth:`close` also stops the control script and disconnects.

    Args:
        host (str): the controller's address.
        limits (SafetyLimits, optional): the enforced limits.
        period (float): the control period the commands are meant for (s), used for the predictive checks.
        control_factory, receive_factory, dashboard_factory: constructors of ur_rtde's
            ``RTDEControlInterface``, ``RTDEReceiveInterface`` and ``DashboardClient`` (default: ur_rtde's;
            tests pass fakes).
        clock, sleep: time functions (tests pass fakes).
    """

    realtime = True

    def __init__(self, host: str, *, limits: SafetyLimits | None = None, period: float = 0.04,
                 control_factory: Callable | None = None, receive_factory: Callable | None = None,
                 dashboard_factory: Callable | None = None, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep, home_tolerance: float = 0.02, home_timeout: float = 30.0):
        self.host = host
        self.limits = limits or SafetyLimits()
        self.period = period
        self._factories = (control_factory, receive_factory, dashboard_factory)
        self._clock, self._sleep = clock, sleep
        self.home_tolerance, self.home_timeout = home_tolerance, home_timeout
        self.control = self.receive = self.dashboard = None
        self._last_q = None
        self._last_timestamp = None
        self._last_advance = None
        self._stops = deque()
        self._closed = False

    # --------------------------------------------------------------- connection
    def connect(self) -> None:
        control_factory, receive_factory, dashboard_factory = self._factories
        if control_factory is None or receive_factory is None:
            try:
                import rtde_control
                import rtde_receive
            except ImportError as err:
                raise ImportError(
                    'the rtde backend needs ur_rtde: pip install "torchrl-reset[robot]" (or pip install ur-rtde)'
                ) from err
            control_factory = control_factory or rtde_control.RTDEControlInterface
            receive_factory = receive_factory or rtde_receive.RTDEReceiveInterface
        self.receive = receive_factory(self.host)
        self.control = control_factory(self.host)
        if dashboard_factory is not None:
            self.dashboard = dashboard_factory(self.host)
        self._check(self.control.setWatchdog(self.limits.watchdog_hz), "setWatchdog")
        atexit.register(self.close)
        self._closed = False

    def _check(self, ok, what: str) -> None:
        if not ok:
            self._safe_stop()
            raise RobotFault(f"ur_rtde {what} returned False: the command was refused (robot stopped or script not running).")

    def _safe_stop(self) -> None:
        try:
            if self.control is not None:
                self.control.speedStop(10.0)
        except Exception as err:  # stopping must never raise on the way out
            log.error("speedStop failed: %r", err)

    # --------------------------------------------------------------- state
    def read_state(self) -> RobotState:
        if not self.receive.isConnected():
            self._safe_stop()
            raise ConnectionLost(f"lost the RTDE link to {self.host}.")
        timestamp = float(self.receive.getTimestamp())
        now = self._clock()
        if self._last_timestamp is None or timestamp > self._last_timestamp:
            self._last_timestamp, self._last_advance = timestamp, now
        elif now - self._last_advance > self.limits.stale_after:
            self._safe_stop()
            raise ConnectionLost(
                f"the robot timestamp has not advanced for {now - self._last_advance:.3f} s: stale state, arm stopped."
            )
        bits = int(self.receive.getSafetyStatusBits())
        fatal = [b for b in SAFETY_FATAL_BITS if bits >> b & 1]
        if fatal:
            self._safe_stop()
            raise RobotFault(f"safety status bits {bits:#b}: emergency stop, violation or fault (bits {fatal}).")
        protective = bool(bits >> SAFETY_PROTECTIVE_STOP_BIT & 1)
        if protective:
            self._count_protective_stop(now)
        q = np.asarray(self.receive.getActualQ(), dtype=np.float64)
        qd = np.asarray(self.receive.getActualQd(), dtype=np.float64)
        self._last_q = q
        return RobotState(q, qd, timestamp, protective_stop=protective)

    def _count_protective_stop(self, now: float) -> None:
        if self._stops and now - self._stops[-1] < 1.0:
            return  # the same stop, still being reported
        self._stops.append(now)
        while self._stops and now - self._stops[0] > self.limits.protective_stop_window:
            self._stops.popleft()
        if len(self._stops) > self.limits.max_protective_stops:
            self._safe_stop()
            raise RobotFault(
                f"{len(self._stops)} protective stops within {self.limits.protective_stop_window:.0f} s: "
                "check the workspace and the limits before going on."
            )

    # --------------------------------------------------------------- motion
    def speedj(self, qd: np.ndarray, acceleration: float | None = None) -> np.ndarray:
        if self._last_q is None:
            self.read_state()
        safe = filter_command(self._last_q, qd, self.period, self.limits)
        acc = self.limits.acceleration if acceleration is None else min(float(acceleration), self.limits.acceleration)
        try:
            self._check(self.control.speedJ(safe.tolist(), acc, self.period), "speedJ")
            self._check(self.control.kickWatchdog(), "kickWatchdog")
        except RobotFault:
            raise
        except Exception:
            self._safe_stop()
            raise
        return safe

    def stop(self) -> None:
        self._check(self.control.speedStop(10.0), "speedStop")

    def move_home(self, q_home: np.ndarray, speed: float = 0.2) -> bool:
        """Slow asynchronous ``moveJ`` home, kicking the watchdog; True when within ``home_tolerance``."""
        self._safe_stop()
        self._check(self.control.moveJ(list(map(float, q_home)), float(speed), 0.5, True), "moveJ")
        deadline = self._clock() + self.home_timeout
        while self._clock() < deadline:
            self._check(self.control.kickWatchdog(), "kickWatchdog")
            state = self.read_state()
            if state.protective_stop:
                return False
            if np.max(np.abs(state.q - q_home)) < self.home_tolerance and np.max(np.abs(state.qd)) < 0.01:
                return True
            self._sleep(self.period)
        self._safe_stop()
        return False

    def unlock_protective_stop(self) -> bool:
        if self.dashboard is None:
            return False
        self.dashboard.unlockProtectiveStop()
        return True

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._safe_stop()
        for name, calls in (("control", ("stopScript", "disconnect")), ("receive", ("disconnect",)), ("dashboard", ("disconnect",))):
            interface = getattr(self, name)
            for call in calls:
                if interface is not None and hasattr(interface, call):
                    try:
                        getattr(interface, call)()
                    except Exception as err:
                        log.error("%s.%s failed: %r", name, call, err)

    def now(self) -> float:
        return self._clock()

    def wait_until(self, t: float) -> None:
        remaining = t - self._clock()
        if remaining > 0:
            self._sleep(remaining)


def cup_axis_tilt(q: np.ndarray) -> float:
    """Angle (rad) between the cup's axis (minus the flange z axis) and the world vertical, from the DH model."""
    z = flange_pose(q)[1][:, 2]
    return math.acos(float(np.clip(-z[2], -1.0, 1.0)))

