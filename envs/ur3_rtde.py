"""The real UR3 through ur_rtde (:class:`RTDEBackend`): the RTDE control and receive links, the controller's safety
and robot modes, the watchdogs and the recovery from a protective stop."""
from __future__ import annotations

import atexit
import logging
import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from .ur3_model import flange_pose
from .ur3_safety import SafetyFilter, SafetyLimits

from .ur3_backends import RobotFault, RobotState, UR3Backend

__all__ = ["RTDEBackend", "ConnectionLost", "SAFETY_PROTECTIVE_STOP_BIT", "SAFETY_FATAL_BITS", "ROBOT_MODE_RUNNING",
           "SAFETY_MODE_NAMES", "ROBOT_MODE_NAMES"]

log = logging.getLogger("torchrl_reset_envs.ur3")

# RTDE safety_status_bits (UR RTDE guide): 0 normal, 1 reduced, 2 protective stopped, 3 recovery mode,
# 4 safeguard stopped, 5 system emergency stopped, 6 robot emergency stopped, 7 emergency stopped,
# 8 violation, 9 fault, 10 stopped due to safety
SAFETY_PROTECTIVE_STOP_BIT = 2
SAFETY_FATAL_BITS = (5, 6, 7, 8, 9)
# RTDE robot_mode and safety_mode codes (UR RTDE guide; ur_rtde's docs)
ROBOT_MODE_NAMES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
                    4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}
ROBOT_MODE_RUNNING = 7
SAFETY_MODE_NAMES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
                     6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT",
                     10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE", 12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
                     13: "SYSTEM_THREE_POSITION_ENABLING_STOP"}
SAFETY_MODE_PROTECTIVE_STOP = 3
SAFETY_MODES_RUNNING = (1, 2)  # normal, reduced
SAFETY_MODES_FATAL = (6, 7, 8, 9)  # emergency stops, violation, fault


class ConnectionLost(RobotFault):
    """The link to the controller dropped or its state stopped advancing."""


class RTDEBackend(UR3Backend):
    """The real UR3 through ur_rtde (``pip install "torchrl-reset[robot]"``), with the safety features of ur3.md section 6.

    - every command is the nearest safe velocity to the requested one (:class:`~ur3_safety.SafetyFilter`):
      within the speed cap, reachable in one period, and keeping the arm able to brake inside the
      joint box and the Cartesian box;
    - the controller's watchdog is armed on connection and kicked with every command; a host-side
      watchdog thread also sends ``speedStop`` when no command was sent for
      ``limits.host_watchdog_periods`` control periods (a stalled trainer), and the next command
      resumes normally;
    - every step checks the link (``isConnected``), that the robot timestamp advances, the safety
      status bits, the robot mode and the safety mode. A robot that is not running in normal or
      reduced mode (protective stop, safeguard stop, idle, powered off...) is *halted*: no command
      is sent, the state says so (``RobotState.halted``, ``reason``) and the env ends the episode;
      an emergency stop, a violation, a fault, or more than ``limits.max_protective_stops``
      protective stops within the window raise :class:`RobotFault`;
    - stopping is best-effort: during a protective stop the controller refuses every command,
      ``speedStop`` included, and that is logged, not raised; a command refused while the robot
      reports no halt raises :class:`RobotFault` after ``speedStop``;
    - :meth:`recover` brings a protectively stopped robot back: it waits until the controller
      accepts an unlock (``limits.unlock_after``, 5 s on UR controllers), unlocks through the
      dashboard, re-uploads the control script, checks that the robot runs again and re-arms the
      watchdog;
    - ``speedStop`` is sent on any error, on :meth:`close` and at interpreter exit; :meth:`close`
      also stops the control script and disconnects.

    Args:
        host (str): the controller's address.
        limits (SafetyLimits, optional): the enforced limits.
        period (float): the control period the commands are meant for (s).
        control_factory, receive_factory, dashboard_factory: constructors of ur_rtde's
            ``RTDEControlInterface``, ``RTDEReceiveInterface`` and ``DashboardClient`` (default: ur_rtde's;
            tests pass fakes).
        clock, sleep: time functions (tests pass fakes). The host watchdog thread runs only with
            the default clock.
        home_tolerance, home_timeout: the move home's tolerance (rad) and time limit (s).
    """

    realtime = True

    def __init__(self, host: str, *, limits: SafetyLimits | None = None, period: float = 0.04,
                 control_factory: Callable | None = None, receive_factory: Callable | None = None,
                 dashboard_factory: Callable | None = None, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep, home_tolerance: float = 0.02, home_timeout: float = 30.0,
                 host_watchdog: bool | None = None):
        self.host = host
        self.limits = limits or SafetyLimits()
        self.period = period
        self.filter = SafetyFilter(self.limits, period)
        host_timeout = self.limits.host_watchdog_periods * period
        if host_timeout > 0 and host_timeout >= 1.0 / self.limits.watchdog_hz:
            raise ValueError(
                f"the host watchdog ({host_timeout * 1000:.0f} ms) must act before the controller's "
                f"({1000 / self.limits.watchdog_hz:.0f} ms): lower host_watchdog_periods or watchdog_hz."
            )
        self._factories = (control_factory, receive_factory, dashboard_factory)
        self._clock, self._sleep = clock, sleep
        self.home_tolerance, self.home_timeout = home_tolerance, home_timeout
        self.control = self.receive = self.dashboard = None
        self._last_state: RobotState | None = None
        self._last_timestamp = None
        self._last_advance = None
        self._stops = deque()
        self._stop_started: float | None = None
        self._closed = False
        self._lock = threading.RLock()  # ur_rtde calls from the step and from the watchdog thread
        self._last_command = None
        self._stop_failure_logged_for = None
        self._stop_problem = ""  # why the last speedStop did not go through  # the last command whose following stall logged a failed speedStop
        self._watchdog_stopped = False
        self._watchdog_thread = None
        self._watchdog_quit = threading.Event()
        self._host_watchdog = (clock is time.monotonic) if host_watchdog is None else bool(host_watchdog)
        self.protective_stops = 0
        self.watchdog_stops = 0
        self.refused_commands = 0

    # --------------------------------------------------------------- connection
    def connect(self) -> None:
        if self.control is not None and not self._closed:
            return  # connected already
        control_factory, receive_factory, dashboard_factory = self._factories
        if control_factory is None or receive_factory is None or dashboard_factory is None:
            try:
                import dashboard_client
                import rtde_control
                import rtde_receive
            except ImportError as err:
                raise ImportError(
                    'the rtde backend needs ur_rtde: pip install "torchrl-reset[robot]" (or pip install ur-rtde)'
                ) from err
            control_factory = control_factory or rtde_control.RTDEControlInterface
            receive_factory = receive_factory or rtde_receive.RTDEReceiveInterface
            dashboard_factory = dashboard_factory or dashboard_client.DashboardClient
        self.receive = receive_factory(self.host)
        self.control = control_factory(self.host)
        self.dashboard = dashboard_factory(self.host)
        if hasattr(self.dashboard, "isConnected") and not self.dashboard.isConnected():
            self.dashboard.connect()
        self._check(self.control.setWatchdog(self.limits.watchdog_hz), "setWatchdog")
        atexit.register(self.close)
        self._closed = False
        self._last_command = self._clock()
        if self._host_watchdog and self.limits.host_watchdog_periods > 0:
            self._watchdog_quit.clear()
            self._watchdog_thread = threading.Thread(target=self._watch, name="ur3-host-watchdog", daemon=True)
            self._watchdog_thread.start()

    def _check(self, ok, what: str) -> None:
        if not ok:
            self._safe_stop()
            raise RobotFault(f"ur_rtde {what} returned False: the command was refused (robot stopped or script not running).")

    def _safe_stop(self, quiet: bool = False) -> bool:
        """``speedStop``, best-effort: False when the controller refuses it or the call fails, logged unless
        ``quiet`` (the host watchdog, which retries every check, says it once); ``_stop_problem`` says which."""
        try:
            with self._lock:
                if self.control is None:
                    return False
                ok = bool(self.control.speedStop(10.0))
        except Exception as err:  # stopping must never raise on the way out
            self._stop_problem = f"failed: {err!r}"
            if not quiet:
                log.error("speedStop %s", self._stop_problem)
            return False
        if not ok:
            self._stop_problem = "refused by the controller (it refuses every command during a protective stop)"
            if not quiet:
                log.warning("speedStop %s.", self._stop_problem)
        return ok

    # --------------------------------------------------------------- host watchdog
    def watchdog_timeout(self) -> float:
        """No command for this long (s) makes the host watchdog send ``speedStop``."""
        return self.limits.host_watchdog_periods * self.period

    def check_watchdog(self) -> bool:
        """One check of the host watchdog (its thread calls this); True when it stopped the arm now.

        Once it has stopped the arm, each further check feeds the controller's watchdog, so the
        control script survives the stall and the next command resumes (the arm rests meanwhile)."""
        if self._closed or self.control is None or self._last_command is None:
            return False
        if self._watchdog_stopped:
            try:
                with self._lock:
                    if self._watchdog_stopped:
                        self.control.kickWatchdog()
            except Exception as err:
                log.error("kickWatchdog failed: %r", err)
            return False
        if self._clock() - self._last_command <= self.watchdog_timeout():
            return False
        with self._lock:
            # checked again under the lock: a command may have been sent meanwhile
            if self._watchdog_stopped or self._clock() - self._last_command <= self.watchdog_timeout():
                return False
            idle = self._clock() - self._last_command
            if not self._safe_stop(quiet=True):
                # not stopped: try again at the next check, and never feed the controller's watchdog,
                # which then stops the control script itself; said once per stretch without commands (a
                # protectively stopped controller refuses speedStop for as long as the stop lasts)
                if self._stop_failure_logged_for != self._last_command:
                    self._stop_failure_logged_for = self._last_command
                    log.error("UR3: no command for %.0f ms and speedStop %s (retried every check, said once "
                              "until the next command).", 1000 * idle, self._stop_problem)
                return False
            self._watchdog_stopped = True
            self.watchdog_stops += 1
        log.warning("UR3: no command for %.0f ms: speedStop.", 1000 * idle)
        return True

    def _watch(self) -> None:
        interval = max(self.period / 4, 0.002)
        while not self._watchdog_quit.wait(interval):
            self.check_watchdog()

    # --------------------------------------------------------------- state
    def read_state(self) -> RobotState:
        with self._lock:
            return self._read_state()

    def _read_state(self) -> RobotState:
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
        robot_mode = int(self.receive.getRobotMode())
        safety_mode = int(self.receive.getSafetyMode())
        fatal = [b for b in SAFETY_FATAL_BITS if bits >> b & 1]
        if fatal or safety_mode in SAFETY_MODES_FATAL:
            self._safe_stop()
            raise RobotFault(
                f"safety status bits {bits:#b}, safety mode {safety_mode} ({SAFETY_MODE_NAMES.get(safety_mode, '?')}): "
                "emergency stop, violation or fault; a person must clear it."
            )
        protective = bool(bits >> SAFETY_PROTECTIVE_STOP_BIT & 1) or safety_mode == SAFETY_MODE_PROTECTIVE_STOP
        reason = None
        if protective:
            reason = "protective stop"
            self._count_protective_stop(now)
        elif safety_mode not in SAFETY_MODES_RUNNING:
            reason = f"safety mode {SAFETY_MODE_NAMES.get(safety_mode, safety_mode)}"
        elif robot_mode != ROBOT_MODE_RUNNING:
            reason = f"robot mode {ROBOT_MODE_NAMES.get(robot_mode, robot_mode)}"
        elif not self.control.isProgramRunning():
            reason = "control script not running"
        if not protective:
            self._stop_started = None
        q = np.asarray(self.receive.getActualQ(), dtype=np.float64)
        qd = np.asarray(self.receive.getActualQd(), dtype=np.float64)
        state = RobotState(q, qd, timestamp, protective_stop=protective, robot_mode=robot_mode, safety_mode=safety_mode,
                           halted=reason is not None, reason=reason)
        self._last_state = state
        return state

    def _count_protective_stop(self, now: float) -> None:
        if self._stop_started is not None:
            return  # the same stop, still being reported
        self._stop_started = now
        self.protective_stops += 1
        self._stops.append(now)
        while self._stops and now - self._stops[0] > self.limits.protective_stop_window:
            self._stops.popleft()
        log.warning("UR3: protective stop (%d in the last %.0f s).", len(self._stops), self.limits.protective_stop_window)
        if len(self._stops) > self.limits.max_protective_stops:
            self._safe_stop()
            raise RobotFault(
                f"{len(self._stops)} protective stops within {self.limits.protective_stop_window:.0f} s: "
                "check the workspace and the limits before going on."
            )

    # --------------------------------------------------------------- motion
    def speedj(self, qd: np.ndarray, acceleration: float | None = None) -> np.ndarray:
        state = self.read_state()  # fresh: the filter must see where the arm is now, not before the update
        if state.halted:
            self._last_command = self._clock()
            return np.zeros(6)  # the controller refuses commands now; the env ends the episode
        acc = self.limits.acceleration if acceleration is None else min(float(acceleration), self.limits.acceleration)
        safe = self.filter(state.q, qd, state.qd, acc)  # planned with the acceleration actually sent
        with self._lock:
            try:
                ok = bool(self.control.speedJ(safe.tolist(), acc, self.period)) and bool(self.control.kickWatchdog())
            except Exception:
                self._safe_stop()
                raise
            self._last_command = self._clock()
            self._watchdog_stopped = False
        if not ok:
            self.refused_commands += 1
            # The controller decides from its own state, which the receive stream may show a little
            # later: watch it for up to stale_after before calling the refusal unexplained.
            deadline = self._clock() + self.limits.stale_after
            while True:
                if self.read_state().halted:  # it stopped since the last reading: end the episode, not the run
                    return np.zeros(6)
                if self._clock() >= deadline:
                    break
                self._sleep(min(self.period / 4, self.limits.stale_after))
            self._safe_stop()
            raise RobotFault("ur_rtde speedJ returned False: the command was refused (control script not running?).")
        return safe

    def stop(self) -> None:
        """``speedStop``, best-effort (see :meth:`_safe_stop`). Once the arm is stopped this way the host watchdog
        has nothing to stop: it only feeds the controller's watchdog until the next command (a deliberate pause,
        :meth:`UR3Env.hold`, is no stall)."""
        stopped = self._safe_stop()
        with self._lock:
            self._last_command = self._clock()
            if stopped:
                self._watchdog_stopped = True

    def recover(self) -> bool:
        """Bring a halted robot back to running; True when it runs in normal or reduced mode again.

        A protective stop: wait until ``limits.unlock_after`` seconds after it began (UR controllers
        refuse earlier unlocks), close the safety pop-up, unlock through the dashboard (retried once a
        second while refused), re-upload the control script, wait until it runs and the robot is in
        RUNNING, and re-arm the watchdog. A stopped control script (the controller's watchdog
        tripped) is re-uploaded. Other halts (safeguard stop, idle, powered off) are not cleared
        automatically: False, so that a person is asked.
        """
        state = self.read_state()
        if not state.halted:
            return True
        if state.reason == "control script not running":
            return self._restart_script(self._clock() + self.limits.recovery_timeout)
        if not state.protective_stop:
            log.warning("UR3: %s cannot be cleared automatically.", state.reason)
            return False
        started = self._stop_started if self._stop_started is not None else self._clock()
        deadline = self._clock() + self.limits.recovery_timeout
        self._sleep(max(0.0, started + self.limits.unlock_after - self._clock()))
        unlocked = False
        while not unlocked and self._clock() < deadline:
            try:
                with self._lock:
                    if hasattr(self.dashboard, "closeSafetyPopup"):
                        self.dashboard.closeSafetyPopup()
                    self.dashboard.unlockProtectiveStop()
                unlocked = True
            except RuntimeError as err:  # ur_rtde raises when the controller refuses the unlock
                log.warning("UR3: unlock refused (%s); retrying.", err)
                self._sleep(1.0)
        if not unlocked:
            return False
        return self._restart_script(deadline)

    def _restart_script(self, deadline: float) -> bool:
        """Re-upload the control script, wait until it runs on a running robot, re-arm the watchdog."""
        with self._lock:
            if not self.control.reuploadScript():
                log.error("UR3: re-uploading the control script failed.")
                return False
        while self._clock() < deadline:
            self._sleep(self.period)
            state = self.read_state()
            with self._lock:
                running = bool(self.control.isProgramRunning())
            if running and not state.halted:
                with self._lock:
                    armed = bool(self.control.setWatchdog(self.limits.watchdog_hz))
                self._last_command = self._clock()
                self._watchdog_stopped = False
                return armed
        return False

    def path_is_safe(self, q_from: np.ndarray, q_to: np.ndarray, samples: int = 50) -> bool:
        """Whether the straight joint-space path of a ``moveJ`` from ``q_from`` to ``q_to`` stays inside
        the joint box and keeps the flange inside the Cartesian box (sampled), or at least goes no further
        out than where it starts (a person may have moved the arm outside)."""
        lim = self.limits
        q_from, q_to = np.asarray(q_from, dtype=np.float64), np.asarray(q_to, dtype=np.float64)

        def excess(q):
            p = flange_pose(q)[0]
            joint = np.maximum(np.maximum(q - lim.joint_high, lim.joint_low - q), 0.0)
            cart = np.maximum(np.maximum(p - lim.cartesian_high, lim.cartesian_low - p), 0.0)
            return np.concatenate([joint, cart])

        allowed = excess(q_from) + 1e-9
        return all(np.all(excess(q_from + t * (q_to - q_from)) <= allowed) for t in np.linspace(0.0, 1.0, samples))

    def move_home(self, q_home: np.ndarray, speed: float = 0.2) -> bool:
        """Slow asynchronous ``moveJ`` home, kicking the watchdog; True when within ``home_tolerance``.

        ``moveJ`` does not go through the velocity filter, so its path is checked first
        (:meth:`path_is_safe`); a path that leaves the boxes is not taken (False: a person is asked)."""
        self._safe_stop()
        start = self.read_state()
        if start.halted:
            return False
        if not self.path_is_safe(start.q, q_home):
            log.error("UR3: the joint-space path home leaves the safety boxes; not moving.")
            return False
        with self._lock:
            ok = self.control.moveJ(list(map(float, q_home)), float(speed), 0.5, True)
        if not ok:
            return False
        deadline = self._clock() + self.home_timeout
        while self._clock() < deadline:
            with self._lock:
                self.control.kickWatchdog()
                self._last_command = self._clock()
                self._watchdog_stopped = False
            state = self.read_state()
            if state.halted:
                return False
            if np.max(np.abs(state.q - q_home)) < self.home_tolerance and np.max(np.abs(state.qd)) < 0.01:
                return True
            self._sleep(self.period)
        self._safe_stop()
        return False

    def counters(self) -> dict[str, int]:
        """What the safety layer did so far (protective stops, watchdog stops, filter counts)."""
        return {"protective_stops": self.protective_stops, "watchdog_stops": self.watchdog_stops,
                "refused_commands": self.refused_commands, **self.filter.counters()}

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self.close)
        self._watchdog_quit.set()
        if self._watchdog_thread is not None and self._watchdog_thread is not threading.current_thread():
            self._watchdog_thread.join(timeout=1.0)
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
