"""A fake of ur_rtde that behaves like a UR controller, for the real-arm backend's tests.

One :class:`FakeURController` holds the arm and the controller's state; ``control()``,
``receive()`` and ``dashboard()`` hand out objects with the methods, signatures and return
conventions of ur_rtde 1.6's ``RTDEControlInterface``, ``RTDEReceiveInterface`` and
``DashboardClient``. What it does, as a UR controller does (ur3.md sections 1 and 6):

- time is the ``clock`` given (fake or real); the arm moves between calls: ``speedJ`` ramps every
  joint to its target with the leading axis at the given acceleration and the others scaled
  (URScript ``speedj``), ``speedStop`` decelerates to rest, ``moveJ(asynchronous=True)`` moves to a
  pose at the given joint speed;
- a **protective stop** (the flange going out of ``pstop_box``, or :meth:`protective_stop`) stops the
  arm at once, sets safety mode 3 and status bit 2, and stops the control script: from then on every
  command returns False (``speedStop`` included, it goes through the same command path) until the
  stop is unlocked *and* the script is re-uploaded. ``unlockProtectiveStop`` raises RuntimeError
  with the controller's refusal for the first 5 s after the stop, as ur_rtde does;
- the **watchdog** set with ``setWatchdog(f)`` stops the control script (and the arm) when no
  ``kickWatchdog`` came for 1/f s; the script then refuses commands until re-uploaded;
- ``robot_mode`` (7 RUNNING, 5 IDLE, 3 POWER_OFF...) and ``safety_mode`` can be changed by a test;
  a robot that is not RUNNING in normal or reduced mode stops and refuses commands;
- :meth:`stall` freezes the receive side (its timestamp and values stop changing, as when the link
  hangs), and ``connected = False`` drops the link (the last values keep being returned).
"""
from __future__ import annotations

import threading

import numpy as np

from torchrl_reset_envs.ur3_model import HOME_Q, flange_pose

RUNNING, IDLE, POWER_OFF = 7, 5, 3
NORMAL, REDUCED, PROTECTIVE_STOP, SAFEGUARD_STOP, ROBOT_EMERGENCY_STOP = 1, 2, 3, 5, 7
PLAYING, STOPPED = 2, 1
UNLOCK_REFUSAL = ("Unlock protective stop failure: Cannot unlock protective stop until 5s after occurrence. "
                  "Always inspect cause of protective stop before unlocking")


class FakeURController:
    """The controller and the arm behind the three fake ur_rtde interfaces."""

    step = 0.002  # integration step (s)

    def __init__(self, clock, q=None, *, pstop_box=None, script_start_delay: float = 0.1):
        self.clock = clock
        self.q = np.array(HOME_Q if q is None else q, dtype=np.float64)
        self.qd = np.zeros(6)
        self.pstop_box = pstop_box  # (low, high) of the flange, or None
        self.script_start_delay = script_start_delay
        self.robot_mode = RUNNING
        self.safety_mode = NORMAL
        self.program_running = True
        self._script_starts_at = None
        self.connected = True
        self.stalled = False
        self.pstop_time = None
        self.unlocked = True
        self.watchdog_hz = None
        self.last_kick = None
        self.target = np.zeros(6)
        self.acceleration = 1.4
        self.move_target = None
        self.move_speed = 0.0
        self.log: list[tuple] = []  # (time, command, accepted)
        self.protective_stops = 0
        self.watchdog_trips = 0
        self._time = clock()
        self._excess = 0.0
        self._frozen = None
        self._lock = threading.RLock()

    # ------------------------------------------------------------------ time
    def advance(self) -> None:
        """Runs the arm and the controller up to the clock's present."""
        with self._lock:
            now = self.clock()
            while self._time < now:
                dt = min(self.step, now - self._time)
                self._time += dt
                self._tick(dt)

    def _tick(self, dt: float) -> None:
        if self._script_starts_at is not None and self._time >= self._script_starts_at and self._can_run():
            self.program_running, self._script_starts_at = True, None
            self.watchdog_hz = None
            self.target[:] = 0.0
        if (self.program_running and self.watchdog_hz is not None and self.last_kick is not None
                and self._time - self.last_kick > 1.0 / self.watchdog_hz):
            self.watchdog_trips += 1
            self._stop_program()
        if not self._can_run():
            self.qd[:] = 0.0  # a stopped robot holds still (stop category 2 is treated as immediate)
            return
        if self.move_target is not None:
            error = self.move_target - self.q
            lead = float(np.max(np.abs(error)))
            if lead < 1e-6:
                self.q, self.qd[:], self.move_target = self.move_target.copy(), 0.0, None
            else:
                self.qd = error / lead * min(self.move_speed, lead / dt)
        else:
            goal = self.target if self.program_running else np.zeros(6)
            dv = goal - self.qd
            lead = float(np.max(np.abs(dv)))
            if lead > self.acceleration * dt:
                dv *= self.acceleration * dt / lead
            self.qd = self.qd + dv
        self.q = self.q + self.qd * dt
        if self.pstop_box is not None:
            # stop when the flange goes (further) out of the box; back inwards it may move, as a
            # controller lets a robot that was unlocked outside a safety limit move back in
            p = flange_pose(self.q)[0]
            low, high = self.pstop_box
            excess = float(np.max(np.maximum(np.maximum(p - high, low - p), 0.0)))
            if excess > self._excess + 1e-9:
                self._protective_stop()
            self._excess = excess

    def _can_run(self) -> bool:
        return self.robot_mode == RUNNING and self.safety_mode in (NORMAL, REDUCED)

    def _stop_program(self) -> None:
        self.program_running = False
        self.watchdog_hz = None  # "all watchdogs are removed on program stop"
        self.target[:] = 0.0
        self.move_target = None

    # ------------------------------------------------------------------ events a test causes
    def protective_stop(self) -> None:
        with self._lock:
            self.advance()
            self._protective_stop()

    def _protective_stop(self) -> None:
        with self._lock:
            if self.safety_mode == PROTECTIVE_STOP:
                return
            self.safety_mode = PROTECTIVE_STOP
            self.pstop_time = self._time
            self.unlocked = False
            self.protective_stops += 1
            self.qd[:] = 0.0
            self._stop_program()

    def stall(self, stalled: bool = True) -> None:
        with self._lock:
            self.advance()
            self.stalled = stalled
            self._frozen = (self._time, self.q.copy(), self.qd.copy()) if stalled else None

    # ------------------------------------------------------------------ command path
    def command(self, name: str, action=None) -> bool:
        """A command through the control script: refused unless the script runs on a running robot."""
        with self._lock:
            self.advance()
            accepted = self.connected and self.program_running and self._can_run()
            if accepted and action is not None:
                action()
            self.log.append((self._time, name, accepted))
            return accepted

    def names(self, accepted_only: bool = True) -> list[str]:
        return [name for _, name, ok in self.log if ok or not accepted_only]

    def control(self, host=None) -> FakeRTDEControlInterface:
        return FakeRTDEControlInterface(self)

    def receive(self, host=None) -> FakeRTDEReceiveInterface:
        return FakeRTDEReceiveInterface(self)

    def dashboard(self, host=None) -> FakeDashboardClient:
        return FakeDashboardClient(self)


class FakeRTDEControlInterface:
    """ur_rtde's ``RTDEControlInterface``: commands return False when refused and never raise for it."""

    def __init__(self, controller: FakeURController):
        self.c = controller

    def setWatchdog(self, min_frequency: float = 10.0) -> bool:
        def arm():
            self.c.watchdog_hz, self.c.last_kick = float(min_frequency), self.c._time
        return self.c.command("setWatchdog", arm)

    def kickWatchdog(self) -> bool:
        def kick():
            self.c.last_kick = self.c._time
        return self.c.command("kickWatchdog", kick)

    def speedJ(self, qd, acceleration: float = 0.5, time: float = 0.0) -> bool:
        if not 0.0 <= acceleration <= 40.0:
            raise RuntimeError(f"speedJ: acceleration {acceleration} outside [0, 40]")  # ur_rtde's range check
        qd = np.asarray(qd, dtype=np.float64)

        def go():
            self.c.move_target = None
            self.c.target, self.c.acceleration = qd.copy(), float(acceleration)
        return self.c.command("speedJ", go)

    def speedStop(self, a: float = 10.0) -> bool:
        def stop():
            self.c.move_target = None
            self.c.target, self.c.acceleration = np.zeros(6), float(a)
        return self.c.command("speedStop", stop)

    def moveJ(self, q, speed: float = 1.05, acceleration: float = 1.4, asynchronous: bool = False) -> bool:
        q = np.asarray(q, dtype=np.float64)

        def move():
            self.c.move_target, self.c.move_speed = q.copy(), float(speed)
        return self.c.command("moveJ", move)

    def isProgramRunning(self) -> bool:
        self.c.advance()
        return self.c.program_running

    def reuploadScript(self) -> bool:
        with self.c._lock:
            self.c.advance()
            self.c.log.append((self.c._time, "reuploadScript", True))
            self.c._stop_program()
            self.c._script_starts_at = self.c._time + self.c.script_start_delay  # it runs shortly after, if it can
            return self.c.connected

    def stopScript(self) -> None:
        with self.c._lock:
            self.c.log.append((self.c._time, "stopScript", True))
            self.c._stop_program()

    def isConnected(self) -> bool:
        return self.c.connected

    def disconnect(self) -> None:
        self.c.log.append((self.c._time, "disconnect", True))


class FakeRTDEReceiveInterface:
    """ur_rtde's ``RTDEReceiveInterface``: stale values (not errors) after a drop or a stall."""

    def __init__(self, controller: FakeURController):
        self.c = controller
        self._last = None

    def _sample(self):
        c = self.c
        c.advance()
        if c.connected and not c.stalled:
            self._last = (c._time, c.q.copy(), c.qd.copy(), c.robot_mode, c.safety_mode)
        elif self._last is None:
            self._last = (c._time, c.q.copy(), c.qd.copy(), c.robot_mode, c.safety_mode)
        return self._last

    def isConnected(self) -> bool:
        return self.c.connected

    def getTimestamp(self) -> float:
        return float(self._sample()[0])

    def getActualQ(self) -> list[float]:
        return list(self._sample()[1])

    def getActualQd(self) -> list[float]:
        return list(self._sample()[2])

    def getRobotMode(self) -> int:
        return int(self._sample()[3])

    def getSafetyMode(self) -> int:
        return int(self._sample()[4])

    def getSafetyStatusBits(self) -> int:
        mode = self._sample()[4]
        bits = {NORMAL: 1, REDUCED: 1 << 1, PROTECTIVE_STOP: 1 << 2, SAFEGUARD_STOP: 1 << 4}.get(mode, 0)
        if mode == ROBOT_EMERGENCY_STOP:
            bits = 1 << 6 | 1 << 7
        return bits

    def getRuntimeState(self) -> int:
        self.c.advance()
        return PLAYING if self.c.program_running else STOPPED

    def disconnect(self) -> None:
        pass


class FakeDashboardClient:
    """ur_rtde's ``DashboardClient``: ``unlockProtectiveStop`` raises RuntimeError when the controller refuses."""

    def __init__(self, controller: FakeURController):
        self.c = controller
        self._connected = False

    def connect(self, timeout_ms: int = 2000) -> None:
        if not self.c.connected:
            raise RuntimeError("Timeout connecting to UR dashboard server.")
        self._connected = True

    def isConnected(self) -> bool:
        return self._connected

    def unlockProtectiveStop(self) -> None:
        c = self.c
        with c._lock:
            c.advance()
            if c.safety_mode == PROTECTIVE_STOP:
                if c._time - c.pstop_time < 5.0:
                    c.log.append((c._time, "unlockProtectiveStop", False))
                    raise RuntimeError(UNLOCK_REFUSAL)
                c.safety_mode, c.unlocked = NORMAL, True
            c.log.append((c._time, "unlockProtectiveStop", True))

    def closeSafetyPopup(self) -> None:
        self.c.log.append((self.c._time, "closeSafetyPopup", True))

    def robotmode(self) -> str:
        names = {RUNNING: "RUNNING", IDLE: "IDLE", POWER_OFF: "POWER_OFF"}
        return f"Robotmode: {names.get(self.c.robot_mode, str(self.c.robot_mode))}"

    def disconnect(self) -> None:
        self._connected = False


__all__ = ["FakeURController", "UNLOCK_REFUSAL", "RUNNING", "IDLE", "POWER_OFF"]
