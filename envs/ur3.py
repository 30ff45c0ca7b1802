"""ur3-peg and ur3-reacher: the UR3 arm as a torchrl environment, on a MuJoCo twin or the real arm."""
from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Callable

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from ._mujoco import tolerance
from .ur3_backends import RobotState, SafetyLimits, SimBackend, SimRealtimeBackend, UR3Backend, cup_axis_tilt
from .ur3_rtde import RTDEBackend
from .ur3_model import CUP_RADIUS, HOME_Q, PEG_LENGTH, flange_pose

#: the control-period histogram's bins: 0.5 ms wide up to 1 s (2000 bins), then one bin beyond
PERIOD_BIN, PERIOD_BINS = 0.0005, 2000

__all__ = ["UR3Env", "sim_manual_reset", "console_manual_reset", "PEG_TARGET", "REACHER_GOAL"]

log = logging.getLogger("torchrl_reset_envs.ur3")

HOME_FLANGE = flange_pose(HOME_Q)[0]
#: where ur3-peg's tip should go: on the table (z = 0), 0.2 m beside the home tip position
PEG_TARGET = np.array([0.3, 0.0, 0.0])
#: ur3-reacher's goal for the flange: 0.4 m from its home position
REACHER_GOAL = HOME_FLANGE + np.array([0.0, 0.4, 0.0])


def sim_manual_reset(env: UR3Env) -> None:
    """The simulated manual reset: the arm back home at rest, the stick back upright."""
    env.backend.move_home(HOME_Q, speed=0.0)


def console_manual_reset(env: UR3Env, prompt: Callable[[str], str] = input, attempts: int = 3) -> None:
    """The real-robot manual reset: recover the robot, move home slowly, verify; a person only where needed.

    1. Stop (best-effort: a protectively stopped controller refuses even ``speedStop``).
    2. A halted robot (protective stop) is recovered by the backend (:meth:`RTDEBackend.recover`:
       wait the controller's 5 s, unlock through the dashboard, re-upload the control script, check
       that it runs). Only when that fails (or the halt is one software may not clear, such as a
       safeguard stop or a powered-off robot) is the person at the console asked to clear it.
    3. A spilled stick (ur3-reacher) is put back by the person.
    4. Up to ``attempts`` slow moves home; if they all fail, the person brings the arm near home.
    """
    backend = env.backend
    backend.stop()
    state = backend.read_state()
    if state.halted and not backend.recover():
        prompt(f"UR3: {state.reason} that could not be cleared automatically. Clear it on the teach pendant "
               "(check the cell first), then press Enter.")
        if not backend.recover():
            raise RuntimeError(f"UR3: the robot is still halted ({backend.read_state().reason}); stopping.")
    if env.task == "reacher" and env.spilled:
        prompt("UR3: the stick is spilled. Put it back upright in the cup, then press Enter.")
    for _ in range(attempts):
        if backend.move_home(HOME_Q, speed=env.home_speed):
            return
        if backend.read_state().halted and not backend.recover():
            break
    prompt(f"UR3: could not reach home after {attempts} slow moves. Bring the arm near home (freedrive), then press Enter.")
    if backend.read_state().halted:
        backend.recover()
    if not backend.move_home(HOME_Q, speed=env.home_speed):
        raise RuntimeError("UR3: the arm did not reach home after the person's help; stopping.")


class UR3Env(EnvBase):
    """The UR3 arm for ur3-peg and ur3-reacher, at 25 Hz, on a MuJoCo twin (``backend="sim"`` in simulated time,
    ``"sim_realtime"`` in wall-clock time) or the real arm (``"rtde"``).

    ==================  ==========================================================================
    observation         0-5 cos of the joint angles, 6-11 sin of them; reacher: 12 the stick status
                        (0 upright, 1 spilled)
    action (6)          joint velocities (rad/s) in [-speed_limit, speed_limit], sent as ``speedj``
                        with acceleration ``acceleration``, one every ``period`` (0.04 s)
    forward reward      peg: ``Cond(d; 0, 0.01, 0.2)``, d = distance from the peg's tip (0.3 m along
                        the flange's z axis) to the target spot (0.3, 0, 0) on the table.
                        reacher: ``Cond(d; 0, 0.02, 0.4)``, d = distance from the flange to the goal
                        0.4 m from its home position (position only)
    reset_success       every joint within ``home_tolerance`` (0.05 rad) of home; reacher: and the
                        stick not spilled
    reset_reward        ``(0.8 [reset_success] + 0.2 Cond(|q - home|; 0, 0.05, 1)) (1 - spilled)``
    irrecoverable       reacher: the stick spilled (latched until a manual reset); peg: none
    terminated          when the robot halts (real arm: a protective or safeguard stop, a robot that
                        is not RUNNING in normal or reduced mode); never in simulation
    start state         home: flange pointing down 0.4 m above the table, at rest (no noise)
    H_f, p_thresh       100 (4 s), 0.1
    ==================  ==========================================================================

    Spilled (sim): the stick leans more than ``spill_angle`` (60 degrees) from the cup's axis or its
    base leaves the cup. On the real arm, ``stick_sensor(env, state) -> bool`` reports it; the
    default declares a spill when the cup's axis tilts more than ``spill_angle`` from vertical.

    Real time: on a real-time backend, :meth:`step` sends the action at once, then waits for the end
    of the 40 ms period and reads the state. Between two steps the trainer has :meth:`time_left`
    seconds; a step called after that counts as an overrun (``overruns``), with a warning, and the
    period restarts from then. The time between successive commands is kept as a histogram
    (:meth:`control_period_stats`: its median and 99th percentile). The wall-clock twin
    (``"sim_realtime"``) is real-time in this sense: the arm runs while the trainer computes.

    Manual resets (``env.reset()``) call ``manual_reset(env)``: by default
    :func:`sim_manual_reset` in simulation and :func:`console_manual_reset` on the real arm.

    Args:
        task (str): ``"peg"`` or ``"reacher"``.
        backend (str or UR3Backend): ``"sim"`` (default), ``"sim_realtime"``, ``"rtde"`` (needs ``host``), or
            an instance.
        host (str, optional): the controller's address for ``"rtde"``.
        speed_limit (float): the action bound (rad/s). Defaults to 0.5.
        acceleration (float): the ``speedj`` acceleration (rad/s^2). Defaults to 1.4.
        period (float): the control period (s). Defaults to 0.04.
        home_tolerance (float): the at-home tolerance per joint (rad). Defaults to 0.05.
        home_speed (float): joint speed of the slow move home on the real arm (rad/s). Defaults to 0.2.
        spill_angle (float): see above, in radians. Defaults to 60 degrees.
        manual_reset, stick_sensor (callable, optional): see above.
        limits (SafetyLimits, optional): the real backend's safety limits (``"rtde"``); with ``"sim"``
            the twin filters its commands the same way (by default it does not).

    Examples:
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_reset_envs import UR3Env
        >>> env = UR3Env("reacher")
        >>> check_env_specs(env)
        >>> td = env.reset()
        >>> td["observation"].shape, td["reset_success"].item(), td["irrecoverable"].item()
        (torch.Size([13]), True, False)
    """

    forward_horizon = 100
    p_thresh = 0.1

    def __init__(self, task: str = "peg", backend: str | UR3Backend = "sim", *, host: str | None = None,
                 speed_limit: float = 0.5, acceleration: float = 1.4, period: float = 0.04, home_tolerance: float = 0.05,
                 home_speed: float = 0.2, spill_angle: float = math.radians(60),
                 manual_reset: Callable[[UR3Env], None] | None = None,
                 stick_sensor: Callable[[UR3Env, RobotState], bool] | None = None,
                 limits: SafetyLimits | None = None, device=None):
        if task not in ("peg", "reacher"):
            raise ValueError(f"task must be 'peg' or 'reacher', got {task!r}.")
        if not 0 < speed_limit <= math.pi:
            raise ValueError(f"speed_limit must lie in (0, pi] rad/s, got {speed_limit}.")
        if period <= 0:
            raise ValueError(f"period must be > 0, got {period}.")
        super().__init__(device=device, batch_size=torch.Size([]))
        self.task = task
        if isinstance(backend, UR3Backend):
            self.backend = backend
        elif backend == "sim":
            self.backend = SimBackend(task, limits=limits, period=period)
        elif backend == "sim_realtime":
            self.backend = SimRealtimeBackend(task, limits=limits, period=period)
        elif backend == "rtde":
            if not host:
                raise ValueError("backend='rtde' needs host=<the controller's address>.")
            self.backend = RTDEBackend(host, limits=limits, period=period)
        else:
            raise ValueError(f"backend must be 'sim', 'sim_realtime', 'rtde' or a UR3Backend, got {backend!r}.")
        self.speed_limit, self.acceleration, self.period = float(speed_limit), float(acceleration), float(period)
        self.home_tolerance, self.home_speed, self.spill_angle = float(home_tolerance), float(home_speed), float(spill_angle)
        sim = isinstance(self.backend, SimBackend)
        self.manual_reset = manual_reset or (sim_manual_reset if sim else console_manual_reset)
        self.stick_sensor = stick_sensor
        self.overruns = 0
        self.halts = 0
        self.period_histogram = np.zeros(PERIOD_BINS + 1, dtype=np.int64)  # 0.5 ms bins; the last: beyond 1 s
        self._last_command = None
        self._held = False
        self.spilled = False
        self._deadline = 0.0
        self._last_warning = -math.inf
        obs_dim = 13 if task == "reacher" else 12
        flag = Categorical(2, shape=(1,), dtype=torch.bool, device=self.device)
        self.observation_spec = Composite(
            observation=Unbounded(shape=(obs_dim,), device=self.device),
            reset_success=flag.clone(), irrecoverable=flag.clone(),
            reset_reward=Unbounded(shape=(1,), device=self.device), device=self.device,
        )
        self.action_spec = Bounded(-self.speed_limit, self.speed_limit, shape=(6,), device=self.device)
        self.reward_spec = Unbounded(shape=(1,), device=self.device)
        self.backend.connect()

    # ------------------------------------------------------------------ task quantities
    def tip_position(self, q: np.ndarray) -> np.ndarray:
        p, rot = flange_pose(q)
        return p + PEG_LENGTH * rot[:, 2]

    def _spilled_now(self, state: RobotState) -> bool:
        if self.task != "reacher":
            return False
        if self.stick_sensor is not None:
            return bool(self.stick_sensor(self, state))
        if "stick_tilt" in state.extra:
            return state.extra["stick_tilt"] > self.spill_angle or state.extra["stick_offset"] > CUP_RADIUS + 0.01
        return cup_axis_tilt(state.q) > self.spill_angle

    def _observe(self, state: RobotState) -> TensorDict:
        q = state.q
        self.spilled = bool(self.spilled or self._spilled_now(state))
        parts = [np.cos(q), np.sin(q)] + ([[float(self.spilled)]] if self.task == "reacher" else [])
        distance_home = float(np.linalg.norm(q - HOME_Q))
        at_home = bool(np.max(np.abs(q - HOME_Q)) < self.home_tolerance and not self.spilled)
        reset_reward = (0.8 * at_home + 0.2 * tolerance(distance_home, 0.0, 0.05, 1.0)) * (1.0 - self.spilled)
        dev = self.device
        return TensorDict(
            observation=torch.as_tensor(np.concatenate(parts), dtype=torch.float32, device=dev),
            reset_success=torch.tensor([at_home], device=dev),
            irrecoverable=torch.tensor([self.spilled], device=dev),
            reset_reward=torch.tensor([reset_reward], dtype=torch.float32, device=dev),
            done=torch.tensor([state.halted], device=dev),
            terminated=torch.tensor([state.halted], device=dev),
        )

    def forward_reward(self, q: np.ndarray) -> float:
        if self.task == "peg":
            return tolerance(float(np.linalg.norm(self.tip_position(q) - PEG_TARGET)), 0.0, 0.01, 0.2)
        return tolerance(float(np.linalg.norm(flange_pose(q)[0] - REACHER_GOAL)), 0.0, 0.02, 0.4)

    # ------------------------------------------------------------------ EnvBase
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        self.manual_reset(self)
        self.spilled = False
        state = self.backend.read_state()
        self._deadline = self.backend.now()
        self._last_command = None  # a manual reset's time is no control period
        return self._observe(state)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        if action.shape != (6,):
            raise ValueError(f"UR3Env expects an action of shape (6,), got {tuple(action.shape)}.")
        qd = action.detach().cpu().double().numpy()
        if not np.all(np.isfinite(qd)):
            raise ValueError(f"UR3Env got a non-finite action (NaN or inf): {qd.tolist()}.")
        qd = np.clip(qd, -self.speed_limit, self.speed_limit)
        target = self._deadline + self.period
        now = self.backend.now()  # the trainer is back
        # the arm followed its last command meanwhile; the wall-clock twin simulates that span now, before the new
        # command, and the time it takes is the twin's, not the trainer's: a fresh period starts after it
        self.backend.idle()
        sent = self.backend.now()
        if self._held:  # after a deliberate hold the period starts afresh: no overrun, no period measured
            self._held, self._last_command, target = False, None, sent + self.period
        elif now > target:
            self._overrun(now - self._deadline)
            target = sent + self.period
        if self._last_command is not None:
            self._record_period(sent - self._last_command)
        self._last_command = sent
        self.backend.speedj(qd, self.acceleration)
        self.backend.wait_until(target)
        self._deadline = target
        state = self.backend.read_state()
        out = self._observe(state)
        out.set("reward", torch.tensor([self.forward_reward(state.q)], dtype=torch.float32, device=self.device))
        if state.halted:
            self.halts += 1
            self.backend.stop()  # best-effort: a protectively stopped controller refuses it
            log.warning("UR3: %s: the episode ends.", state.reason)
        return out

    def _overrun(self, waited: float) -> None:
        self.overruns += 1
        now = self.backend.now()
        if now - self._last_warning > 5.0:
            self._last_warning = now
            warnings.warn(
                f"UR3Env: {waited * 1000:.0f} ms between steps, more than the {self.period * 1000:.0f} ms period "
                f"({self.overruns} overruns so far): the previous command ran longer than one period.",
                RuntimeWarning,
                stacklevel=3,
            )

    def safety_counters(self) -> dict[str, int]:
        """Episodes ended by a halted robot, plus the backend's counters (protective stops, host
        watchdog stops, safety-filter counts)."""
        return {"halts": self.halts, **self.backend.counters()}

    def hold(self) -> None:
        """Stops the arm for a deliberate pause between steps (the trainer waiting at an episode boundary for its
        learner, an evaluation, a checkpoint): the next step starts a fresh period, not an overrun. Call
        :meth:`idle` now and then during a long pause (the wall-clock twin then simulates the stopped arm as the
        pause goes, not all at once before the next command)."""
        self.backend.stop()
        self._held = True

    def idle(self) -> None:
        """Brings the arm up to the present while the trainer is away (see :meth:`UR3Backend.idle`)."""
        self.backend.idle()

    def _record_period(self, seconds: float) -> None:
        # a period exactly on a bin's edge (40 ms) goes to the bin it starts, whatever the float rounding
        self.period_histogram[min(int(seconds / PERIOD_BIN + 1e-6), PERIOD_BINS)] += 1

    def control_period_stats(self) -> dict[str, float | int | None]:
        """The time between successive commands (a manual reset between two is not counted): ``median_ms`` and ``p99_ms`` (the upper edge
        of their 0.5 ms bin; None before two commands), and how many were measured."""
        counts = self.period_histogram
        total = int(counts.sum())
        if not total:
            return {"median_ms": None, "p99_ms": None, "measured": 0}
        cumulative = np.cumsum(counts)

        def quantile(q: float) -> float:
            index = int(np.searchsorted(cumulative, q * total))
            return (index + 1) * PERIOD_BIN * 1000 if index < PERIOD_BINS else math.inf

        return {"median_ms": quantile(0.5), "p99_ms": quantile(0.99), "measured": total}

    def time_left(self) -> float:
        """Seconds until the next step must be called to keep the control period."""
        return self._deadline + self.period - self.backend.now()

    def _set_seed(self, seed: int | None) -> None:
        return None  # the start state has no noise

    def close(self, *, raise_if_closed: bool = True) -> None:
        try:
            self.backend.close()
        finally:
            super().close(raise_if_closed=raise_if_closed)

    # ------------------------------------------------------------------ simulator state (sim backend)
    def get_simulator_state(self) -> dict | None:
        """The twin's state plus the spill flag and the period clock; None on a real arm (it cannot be saved)."""
        if not isinstance(self.backend, SimBackend):
            return None
        return {**self.backend.get_simulator_state(), "spilled": self.spilled, "deadline": self._deadline}

    def set_simulator_state(self, state: dict | None) -> None:
        if state is None:
            return
        self.backend.set_simulator_state(state)
        self.spilled = bool(state["spilled"])
        self._deadline = float(state["deadline"])
