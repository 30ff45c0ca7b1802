"""How :class:`UR3Env` talks to an arm: one small interface and the MuJoCo twin (the real arm: :mod:`.ur3_rtde`).

Both backends speak joint angles (rad), joint velocities (rad/s) and a ``speedj`` command: "move
every joint at these velocities, reaching them with a bounded acceleration, until told otherwise".
"""
from __future__ import annotations

import abc
import logging
import math
import time
from dataclasses import dataclass, field

import mujoco
import numpy as np
import torch

from ._mujoco import get_physics, set_physics
from .ur3_model import HOME_Q, JOINT_HIGH, JOINT_LOW, VELOCITY_LIMITS, build_ur3_spec, flange_pose
from .ur3_safety import SafetyFilter, SafetyLimits, filter_command

__all__ = [
    "RobotState", "UR3Backend", "SimBackend", "SimRealtimeBackend", "SafetyLimits", "RobotFault", "SafetyFilter", "filter_command",
    "cup_axis_tilt",
]

log = logging.getLogger("torchrl_reset_envs.ur3")



class RobotFault(RuntimeError):
    """The arm is in a state where nothing may move (emergency stop, safety violation, fault, failed command)."""




@dataclass
class RobotState:
    """One reading of the arm."""

    q: np.ndarray
    qd: np.ndarray
    timestamp: float
    protective_stop: bool = False
    robot_mode: int = 7
    safety_mode: int = 1
    #: the robot is not running in normal or reduced mode: it takes no command; the episode ends
    halted: bool = False
    reason: str | None = None
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

    def recover(self) -> bool:
        """Bring a halted robot back to running (see :meth:`RTDEBackend.recover`); True when it runs."""
        return not self.read_state().halted

    def counters(self) -> dict[str, int]:
        """What the backend's safety layer did (protective stops, watchdog stops...)."""
        return {}

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

    def idle(self) -> None:
        """Brings the arm up to the present while the trainer is away from it (busy, or waiting with the arm
        held): a real arm and a simulated-time twin have nothing to do; the wall-clock twin runs its physics over
        the time that passed, under the command the arm was following."""


# ---------------------------------------------------------------------------------------------- sim
class SimBackend(UR3Backend):
    """The MuJoCo twin (see :mod:`ur3_model`), with ``speedj`` emulated.

    A velocity reference follows the commanded velocities with the leading axis accelerating at
    ``acceleration`` and the others scaled to arrive at the same time (URScript ``speedj``); its
    integral drives stiff position servos. Physics runs at 2 ms steps. ``restore_home`` is the
    simulated manual reset: the arm at ``q_home``, at rest, the stick back upright in its cup.

    With ``limits`` (a :class:`SafetyLimits`), every command goes through the real backend's
    :class:`SafetyFilter` first (for ``period``-long commands), so the twin shows what the filter
    lets the real arm do; ``limits.acceleration`` then bounds the acceleration too.
    """

    realtime = False

    def __init__(self, task: str = "peg", *, timestep: float = 0.002, kp: float = 5000.0,
                 limits: SafetyLimits | None = None, period: float = 0.04):
        self.task = task
        self.timestep = timestep
        self.kp = kp
        self.limits = limits
        self.filter = None if limits is None else SafetyFilter(limits, period)
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
        qd = np.asarray(qd, dtype=np.float64)
        if self.filter is not None:
            acceleration = min(float(acceleration), self.limits.acceleration)
            qd = self.filter(self.data.qpos[self._arm_q].copy(), qd, self.data.qvel[self._arm_q].copy(), acceleration)
        self._cmd = np.clip(qd, -VELOCITY_LIMITS, VELOCITY_LIMITS)
        self._acc = float(acceleration)
        return self._cmd.copy()

    def counters(self) -> dict[str, int]:
        return {} if self.filter is None else self.filter.counters()

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
class SimRealtimeBackend(SimBackend):
    """The MuJoCo twin in wall-clock time: the arm runs while the trainer computes, as the real arm does.

    ``now()`` is a monotonic clock (seconds since ``connect``), so :class:`~torchrl_reset_envs.UR3Env` paces its
    steps at the control period on it and counts an overrun whenever the trainer comes back late, exactly as
    on the real backend (``realtime = True``: the recipe's update budget applies). The physics runs on the same
    clock: :meth:`idle` runs it over the wall-clock time since the last call under the command the arm was
    following (the arm keeps executing its last command while the trainer is busy, however long that takes;
    :class:`~torchrl_reset_envs.UR3Env` calls it before each new command and a waiting trainer calls it while it
    waits), and ``wait_until(t)`` runs it up to ``t``, then sleeps until ``t``. A manual reset or a restored
    simulator state ties the physics' time to the clock afresh.

    Args:
        clock, sleep: the monotonic clock and the sleep (tests pass a fake pair); other arguments as
            :class:`SimBackend`.
    """

    realtime = True

    def __init__(self, *args, clock=time.monotonic, sleep=time.sleep, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._clock, self._sleep = clock, sleep
        self._origin = None
        self._offset = 0.0  # the physics' time minus the clock's: the physics has run up to clock time t when
        # its time reads t + offset (to its 2 ms step, without drift however often it is brought up to date)

    def connect(self) -> None:
        if self._origin is None:
            self._origin = self._clock()
        super().connect()
        self._tie_clock()

    def now(self) -> float:
        return self._clock() - self._origin

    def _tie_clock(self) -> None:
        self._offset = float(self.data.time) - self.now()

    def restore_home(self, q_home: np.ndarray) -> None:
        super().restore_home(q_home)
        if self._origin is not None:
            self._tie_clock()

    def set_simulator_state(self, state: dict) -> None:
        super().set_simulator_state(state)
        self._tie_clock()

    def _run_to(self, t: float) -> None:
        SimBackend.wait_until(self, t + self._offset)  # nothing when the physics is there already

    def idle(self) -> None:
        self._run_to(self.now())

    def stop(self) -> None:
        self.idle()  # the arm ran its last command up to the stop
        super().stop()

    def wait_until(self, t: float) -> None:
        self._run_to(t)
        remaining = t - self.now()
        if remaining > 0:
            self._sleep(remaining)


def cup_axis_tilt(q: np.ndarray) -> float:
    """Angle (rad) between the cup's axis (minus the flange z axis) and the world vertical, from the DH model."""
    z = flange_pose(q)[1][:, 2]
    return math.acos(float(np.clip(-z[2], -1.0, 1.0)))

