"""The real UR3's command filter: the nearest safe joint velocity to the commanded one.

Every ``speedj`` command of the real backend goes through :class:`SafetyFilter`. Safe means, for the
velocity ``v`` sent now, with the arm at ``q`` moving at ``w`` (measured):

1. **speed cap**: ``|v_j| <= cap_j``, a fraction of the hardware limits;
2. **reachable in one period**: ``|v_j - w_j| <= a dt``. ``speedj`` ramps the leading axis at ``a``
   and scales the others, so a command within this band is reached within the period on every
   axis, and the predictions below hold;
3. **joint box**: ``q_j + v_j H`` inside ``[joint_low_j, joint_high_j]``;
4. **Cartesian box**: the flange, linearised through the Jacobian ``J`` of the DH model,
   ``p + J v H`` inside the box shrunk by ``cartesian_margin``.

``H`` is the prediction horizon. One period (``H = dt``) ignores that the arm cannot stop at once:
braking from ``w`` at ``a`` takes ``max|w| / a`` and, with ``speedj``'s scaled axes, moves every joint
along a straight line in joint space. With ``H = dt + v_max / a`` (the default; ``v_max`` the
largest cap) the joint-box constraints are an invariant: when they hold for the current motion, the
braking command (the motion scaled down by ``a dt`` on its leading axis, as ``speedj`` brakes)
satisfies them again one period later, so the arm can always stop inside the joint box. For the
Cartesian box the same holds to first order only: the Jacobian changes along the path, and where
that breaks a bound the filter falls back to zero velocity (below). Only the flange point is
constrained (not the tool, the elbow or the wrist), and the true kinematics are checked one period
ahead; the margins absorb the rest, as the closed-loop tests measure.

A face the arm is already beyond (or within the margin of) only forbids moving further out: the
bounds are relaxed to "not outward", so that zero velocity always meets 1, 3 and 4.

The nearest safe velocity, ``argmin ||v - u||`` over these linear constraints, is a small convex
quadratic programme (6 variables, at most 30 constraints) solved by a primal active-set method that
starts from a feasible point (the braking command) and keeps every iterate feasible; a command that
is already safe is returned unchanged. When even the braking command breaks a bound (the arm moves
faster or closer to a face than the invariant allows: tracking errors, the Jacobian changing along a
curved path, a person having moved the arm), or when the true (non-linearised) flange one period
ahead would leave the box, the filter falls back to zero velocity (the arm brakes at ``a`` until
the braking command is feasible again) and counts it in ``fallbacks``.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from .ur3_model import HOME_Q, VELOCITY_LIMITS, flange_pose

__all__ = ["SafetyLimits", "SafetyFilter", "filter_command", "flange_jacobian", "nearest_feasible"]


@dataclass
class SafetyLimits:
    """What the real backend enforces on every command (ur3.md section 6; see :mod:`ur3_safety`).

    Attributes:
        speed_fraction: commanded joint speeds are capped at this fraction of the hardware limits.
        acceleration: the fixed ``speedj`` acceleration (rad/s^2 of the leading axis), at most 40;
            the filter also limits each command's change to ``acceleration * period``.
        joint_low, joint_high: the joint-angle box (rad).
        cartesian_low, cartesian_high: the box (m, world frame) of the flange.
        joint_margin, cartesian_margin: the filter aims at the boxes shrunk by these margins (rad, m),
            so that tracking errors and the linearisation stay inside the boxes themselves.
        horizon: the prediction horizon (s); ``None`` (default): ``period + v_max / acceleration``,
            the horizon that lets the arm always brake inside the boxes.
        watchdog_hz: the controller stops the control script when no command came for ``1 / watchdog_hz``
            seconds (this process died or hung). 5 Hz: slower than the host watchdog, which acts first.
        host_watchdog_periods: the backend's own watchdog sends ``speedStop`` when no command was
            sent for this many control periods (the trainer stalled), then keeps the controller's
            watchdog fed while the arm rests, so that the next command resumes normally (0 turns it off).
        stale_after: the state counts as stale when the robot timestamp has not advanced for this long (s).
        max_protective_stops, protective_stop_window: more stops than this within the window (s) is fatal.
        unlock_after: a protective stop can be unlocked this long after it occurred (s); UR
            controllers refuse earlier unlocks (5 s).
        recovery_timeout: how long recovering from a protective stop may take in all (s).
    """

    speed_fraction: float = 0.25
    acceleration: float = 1.4
    joint_low: np.ndarray = field(default_factory=lambda: HOME_Q - 1.5)
    joint_high: np.ndarray = field(default_factory=lambda: HOME_Q + 1.5)
    cartesian_low: np.ndarray = field(default_factory=lambda: np.array([0.05, -0.45, 0.30]))
    cartesian_high: np.ndarray = field(default_factory=lambda: np.array([0.55, 0.45, 0.75]))
    joint_margin: float = 0.01
    cartesian_margin: float = 0.01
    horizon: float | None = None
    watchdog_hz: float = 5.0
    host_watchdog_periods: float = 3.0
    stale_after: float = 0.1
    max_protective_stops: int = 10
    protective_stop_window: float = 600.0
    unlock_after: float = 5.0
    recovery_timeout: float = 30.0

    def __post_init__(self):
        if not 0.0 < self.speed_fraction <= 1.0:
            raise ValueError(f"speed_fraction must lie in (0, 1], got {self.speed_fraction}.")
        if not 0.0 < self.acceleration <= 40.0:
            raise ValueError(f"acceleration must lie in (0, 40] rad/s^2 (ur_rtde's range), got {self.acceleration}.")
        for name in ("joint_low", "joint_high", "cartesian_low", "cartesian_high"):
            setattr(self, name, np.asarray(getattr(self, name), dtype=np.float64).reshape(-1))
        if self.joint_low.shape != (6,) or self.joint_high.shape != (6,):
            raise ValueError("joint_low and joint_high must have 6 entries.")
        if self.cartesian_low.shape != (3,) or self.cartesian_high.shape != (3,):
            raise ValueError("cartesian_low and cartesian_high must have 3 entries.")
        if np.any(self.joint_low >= self.joint_high) or np.any(self.cartesian_low >= self.cartesian_high):
            raise ValueError("each low bound must lie below its high bound.")
        if self.cartesian_margin < 0 or np.any(2 * self.cartesian_margin >= self.cartesian_high - self.cartesian_low):
            raise ValueError(f"cartesian_margin must be >= 0 and leave room in the box, got {self.cartesian_margin}.")
        if self.joint_margin < 0 or np.any(2 * self.joint_margin >= self.joint_high - self.joint_low):
            raise ValueError(f"joint_margin must be >= 0 and leave room in the box, got {self.joint_margin}.")
        if self.horizon is not None and self.horizon <= 0:
            raise ValueError(f"horizon must be > 0 (s) or None, got {self.horizon}.")
        if self.horizon is not None and self.horizon < self.cap.max() / self.acceleration:
            warnings.warn(
                f"horizon {self.horizon} s is shorter than the time to brake from the speed cap "
                f"({self.cap.max() / self.acceleration:.2f} s at {self.acceleration} rad/s^2): the arm may overshoot the boxes.",
                RuntimeWarning, stacklevel=3,
            )
        if self.host_watchdog_periods < 0:
            raise ValueError(f"host_watchdog_periods must be >= 0, got {self.host_watchdog_periods}.")

    @property
    def cap(self) -> np.ndarray:
        """The speed cap of each joint (rad/s)."""
        return self.speed_fraction * VELOCITY_LIMITS

    def horizon_for(self, period: float, acceleration: float | None = None) -> float:
        """The prediction horizon used with control period ``period`` (s) and ``acceleration``."""
        if self.horizon is not None:
            return float(self.horizon)
        acc = self.acceleration if acceleration is None else float(acceleration)
        return float(period + self.cap.max() / acc)


def flange_jacobian(q: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """3x6 Jacobian of the world flange position (central differences of the DH model)."""
    columns = [(flange_pose(q + dq)[0] - flange_pose(q - dq)[0]) / (2 * eps) for dq in np.eye(6) * eps]
    return np.stack(columns, axis=1)


def nearest_feasible(u: np.ndarray, G: np.ndarray, h: np.ndarray, start: np.ndarray, *, max_iter: int = 200,
                     tol: float = 1e-10) -> tuple[np.ndarray, bool]:
    """``argmin ||v - u||^2`` subject to ``G v <= h``, by a primal active-set method from a feasible ``start``.

    Every iterate stays feasible: each step stops at the first constraint it meets. A constraint joins
    the working set only when the step moves against it by more than ``tol`` relative to both norms,
    so the working set stays linearly independent; among ties the lowest index is taken, and the lowest
    index with a negative multiplier leaves (Bland's rule), which keeps degenerate starts from
    cycling. Returns the point and whether the optimality conditions were met within ``max_iter``
    iterations (when not, the point is still feasible, only perhaps not the nearest).
    """
    v = np.array(start, dtype=np.float64)
    row_norms = np.linalg.norm(G, axis=1)
    working: list[int] = []
    scale = 1.0 + float(np.linalg.norm(u))
    for _ in range(max_iter):
        gradient = v - u
        if working:
            a = G[working]
            multipliers = np.linalg.lstsq(a.T, -gradient, rcond=None)[0]
            step = -gradient - a.T @ multipliers
        else:
            multipliers = np.zeros(0)
            step = -gradient
        step_norm = float(np.linalg.norm(step))
        if step_norm <= tol * scale:
            negative = [k for k, m in enumerate(multipliers) if m < -tol * scale]
            if not negative:
                return v, True  # the KKT conditions hold: the optimum
            working.pop(min(negative, key=lambda k: working[k]))  # Bland: the lowest constraint index
            continue
        rates = G @ step
        slack = np.maximum(h - G @ v, 0.0)
        alpha, blocking = 1.0, None
        for i in np.flatnonzero(rates > tol * row_norms * step_norm):
            if i in working:
                continue
            limit = slack[i] / rates[i]
            if limit < alpha - 1e-15:
                alpha, blocking = limit, int(i)
        v = v + alpha * step
        if blocking is not None:
            working.append(blocking)
    return v, False


class SafetyFilter:
    """Makes velocity commands safe (see the module docstring) and counts what it did.

    Attributes:
        calls: commands filtered. changed: commands that were not already safe.
        fallbacks: commands replaced by zero velocity: even the braking command broke a bound, the
            solver's result failed its final check, or the true flange one period ahead left the box.
    """

    def __init__(self, limits: SafetyLimits, period: float):
        if period <= 0:
            raise ValueError(f"period must be > 0, got {period}.")
        self.limits = limits
        self.period = float(period)
        self.calls = self.changed = self.fallbacks = 0

    def constraints(self, q: np.ndarray, w: np.ndarray, acceleration: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``G, h`` of the constraint set ``G v <= h`` at joints ``q`` moving at ``w``, for ``acceleration``."""
        lim = self.limits
        acc = lim.acceleration if acceleration is None else float(acceleration)
        dt, horizon = self.period, lim.horizon_for(self.period, acc)
        cap, band = lim.cap, acc * dt
        # joint box through the horizon, relaxed to "not outward" beyond a face
        joint_high = np.maximum((lim.joint_high - lim.joint_margin - q) / horizon, 0.0)
        joint_low = np.minimum((lim.joint_low + lim.joint_margin - q) / horizon, 0.0)
        upper = np.minimum.reduce([cap, w + band, joint_high])
        lower = np.maximum.reduce([-cap, w - band, joint_low])
        eye = np.eye(6)
        p = flange_pose(q)[0]
        jac = flange_jacobian(q)
        cart_high = np.maximum((lim.cartesian_high - lim.cartesian_margin - p) / horizon, 0.0)
        cart_low = np.minimum((lim.cartesian_low + lim.cartesian_margin - p) / horizon, 0.0)
        G = np.concatenate([eye, -eye, jac, -jac])
        h = np.concatenate([upper, -lower, cart_high, -cart_low])
        return G, h

    def __call__(self, q: np.ndarray, command: np.ndarray, measured: np.ndarray | None = None,
                 acceleration: float | None = None) -> np.ndarray:
        """The safe velocity nearest to ``command`` for the arm at ``q`` moving at ``measured`` (rad/s),
        for a ``speedj`` sent with ``acceleration`` (default and upper bound: ``limits.acceleration``;
        a gentler acceleration brakes less, so the filter plans with the one actually used)."""
        q = np.asarray(q, dtype=np.float64)
        u = np.asarray(command, dtype=np.float64)
        w = np.zeros(6) if measured is None else np.asarray(measured, dtype=np.float64)
        if q.shape != (6,) or u.shape != (6,) or w.shape != (6,):
            raise ValueError(f"q, command and measured must have 6 entries, got {q.shape}, {u.shape}, {w.shape}.")
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(u)) and np.all(np.isfinite(w))):
            raise ValueError("the safety filter got a non-finite joint angle, command or velocity.")
        acc = self.limits.acceleration if acceleration is None else min(float(acceleration), self.limits.acceleration)
        if not acc > 0:
            raise ValueError(f"acceleration must be > 0, got {acceleration}.")
        self.calls += 1
        G, h = self.constraints(q, w, acc)
        tol = 1e-9
        if np.all(G @ u <= h + tol) and self._true_flange_ok(q, u):
            return u.copy()
        self.changed += 1
        # the braking command: the current motion scaled down by a dt on its leading axis, which is
        # what speedj does on its way to rest (every axis in proportion, the direction kept)
        # (or, failing that, every axis slowed by a dt on its own)
        w_cap = np.clip(w, -self.limits.cap, self.limits.cap)
        lead = float(np.max(np.abs(w_cap)))
        band = acc * self.period
        candidates = (w_cap * max(0.0, 1.0 - band / lead) if lead > 0 else np.zeros(6),
                      w_cap - np.clip(w_cap, -band, band))
        start = next((c for c in candidates if np.all(G @ c <= h + tol)), None)
        if start is None:
            # Even braking as hard as the acceleration allows breaks a bound (the arm moves faster or
            # closer to a face than the invariant allows): brake (zero velocity at acceleration a).
            self.fallbacks += 1
            return np.zeros(6)
        v, _ = nearest_feasible(u, G, h, start)
        if np.any(G @ v > h + tol) or not self._true_flange_ok(q, v):
            self.fallbacks += 1
            return np.zeros(6)
        return v

    def _true_flange_ok(self, q: np.ndarray, v: np.ndarray) -> bool:
        """The flange one period ahead (true DH kinematics) inside the box, or not further out on any axis."""
        lim = self.limits
        p = flange_pose(q)[0]
        nxt = flange_pose(q + v * self.period)[0]
        high_ok = (nxt <= lim.cartesian_high) | (nxt <= p)
        low_ok = (nxt >= lim.cartesian_low) | (nxt >= p)
        return bool(np.all(high_ok & low_ok))

    def counters(self) -> dict[str, int]:
        return {"filtered_commands": self.calls, "changed_commands": self.changed, "filter_fallbacks": self.fallbacks}


def filter_command(q: np.ndarray, qd: np.ndarray, dt: float, limits: SafetyLimits,
                   measured: np.ndarray | None = None) -> np.ndarray:
    """The safe velocity nearest to ``qd`` (one call of a :class:`SafetyFilter`; see the module docstring)."""
    return SafetyFilter(limits, dt)(q, qd, measured)
