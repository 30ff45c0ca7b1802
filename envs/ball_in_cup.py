"""ball-in-cup: catch the ball in the cup, or throw it as far as possible (tasks.md; reconstructed definitions)."""
from __future__ import annotations

import mujoco
import numpy as np

from ._mujoco import MujocoResetEnv, asset_path

__all__ = ["BallInCupEnv"]

GRAVITY = 9.81
STRING_LENGTH = 0.3
#: at-initial-state thresholds (see the class docstring for how they were chosen)
CUP_CENTRE_TOL = 0.05
CUP_SPEED_MAX = 0.5
HANG_DROP_MIN = 0.2
SWING_ENERGY_MAX = 0.05
BALL_IN_CUP_SPEED_MAX = 0.5
_SETTLE_STEPS = 2500  # 5 s of simulated time at 2 ms: the cup's springs and the string are at rest after it


class BallInCupEnv(MujocoResetEnv):
    """ball-in-cup: a cup on sprung x and z slides with a ball on a 0.3 m string.

    ``forward="catch"`` (ball-in-cup-catch) starts with the ball hanging still below the cup and rewards
    having it in the cup; its reset agent must get the ball out and let it settle. ``forward="throw"``
    (ball-in-cup-throw) starts with the ball resting in the cup and rewards its distance from the cup;
    its reset agent must catch the ball again.

    Model: dm_control's ``ball_in_cup.xml`` unchanged (physics timestep 0.002 s, 10 substeps, so a
    control step of 0.02 s; cup slides with stiffness 20 and damping 3; motors with gear 5). Under
    gravity the springs hold the cup 6.4 cm below their rest length; that equilibrium, with the ball
    hanging (catch) or lying in the cup (throw), is found by simulating 5 s without action when the
    env is built, and is called the *centre* below.

    ==================  ==========================================================================
    observation (8)     0 cup x, 1 cup z (m, slide positions, 0 at the springs' rest length),
                        2 ball x, 3 ball z (m, slide positions); 4-7 the same four velocities (m/s)
    action (2)          forces on the cup in [-1, 1] (x, z)
    forward reward      catch: ``in_target``, 1 when the ball is inside the cup (ball centre within
                        target half-size 0.05 minus ball radius 0.025 of the cup's target site, in
                        x and z), else 0. throw: ``clip(|ball - target site| / 0.3, 0, 1)``
    reset_success       catch (ball hanging still): cup within 0.05 of the centre in x and z, cup
                        speed < 0.5, ball at least 0.2 below the string's anchor in the cup, and
                        swing energy ``|v_ball|^2 / 2 + g (z_ball - z_lowest)`` < 0.05 J/kg, with
                        ``z_lowest`` = anchor height - 0.3 (about a 10 degree swing; it also bounds
                        the ball speed below 0.32 m/s). throw: ``in_target`` and ball speed < 0.5
    reset_reward        ``0.8 [reset_success] + 0.2 (1 - clip(|ball - ball_0| / 0.3, 0, 1))``, with
                        ``ball_0`` the ball's position at the settled start
    irrecoverable       none (always False)
    start state         the settled centre state; the whole system shifted by U(-0.01, 0.01) in x;
                        velocities N(0, 0.01)
    H_f, p_thresh       100, 0.1
    ==================  ==========================================================================

    The paper only names the tasks; these definitions are ours, reconstructed from it (tasks.md).
    The swing-energy test is there because a swinging ball passes through still, high points at
    each end of its swing: a speed test alone would pass it there, the energy does not change with
    the phase. A ball swinging 30 degrees (0.39 J/kg) fails at every phase; a settled one (0 J/kg)
    passes.

    Args:
        forward (str): ``"catch"`` or ``"throw"``.

    Examples:
        >>> from torchrl_reset_envs import BallInCupEnv
        >>> env = BallInCupEnv("throw")
        >>> obs, info = env.reset(seed=0)
        >>> env.in_target(), bool(info["reset_success"])
        (True, True)
    """

    frame_skip = 10
    forward_horizon = 100
    p_thresh = 0.1
    default_camera = "cam0"

    def __init__(self, forward: str = "catch", **kwargs):
        if forward not in ("catch", "throw"):
            raise ValueError(f"forward must be 'catch' or 'throw', got {forward!r}.")
        self.forward = forward
        super().__init__(**kwargs)

    def _compiled(self) -> None:
        m = self.model
        self._ball_body = m.body("ball").id
        self._ball_site = m.site("ball").id
        self._cup_site = m.site("cup").id
        self._target_site = m.site("target").id
        self._target_half = m.site_size[self._target_site][[0, 2]].copy()
        self._ball_radius = float(m.geom_size[m.geom("ball").id][0])
        # Settle the start state once, without action.
        data = mujoco.MjData(m)
        if self.forward == "throw":
            # Ball just above the cup's bottom (cup bottom capsule top at z = 0.6 - 0.1 + 0.008).
            data.qpos[3] = 0.6 - 0.1 + 0.008 + self._ball_radius + 0.01 - 0.2
        mujoco.mj_step(m, data, nstep=_SETTLE_STEPS)
        self._start_qpos = data.qpos.copy()
        self._centre = data.qpos[:2].copy()
        self._ball_start = data.xpos[self._ball_body][[0, 2]].copy()

    def _build_spec(self) -> mujoco.MjSpec:
        return mujoco.MjSpec.from_file(asset_path("dm_control", "ball_in_cup.xml"))

    def _reset_state(self) -> None:
        rng = self.np_random
        shift = rng.uniform(-0.01, 0.01)
        qpos = self._start_qpos.copy()
        qpos[[0, 2]] += shift
        self.data.qpos[:] = qpos
        self.data.qvel[:] = rng.normal(0.0, 0.01, size=self.model.nv)

    def _observation(self) -> np.ndarray:
        return np.concatenate([self.data.qpos, self.data.qvel])

    # ------------------------------------------------------------------ task quantities
    def ball_position(self) -> np.ndarray:
        """Ball centre (x, z) in the world frame."""
        return self.data.xpos[self._ball_body][[0, 2]].copy()

    def ball_to_target(self) -> np.ndarray:
        return self.data.site_xpos[self._target_site][[0, 2]] - self.ball_position()

    def in_target(self) -> bool:
        return bool(np.all(np.abs(self.ball_to_target()) < self._target_half - self._ball_radius))

    def swing_energy(self) -> float:
        """Ball's kinetic plus potential energy per unit mass above the lowest point the string allows."""
        v_ball = self.data.qvel[2:4]
        z_lowest = float(self.data.site_xpos[self._cup_site][2]) - STRING_LENGTH
        return 0.5 * float(v_ball @ v_ball) + GRAVITY * (float(self.ball_position()[1]) - z_lowest)

    def _at_initial_state(self) -> bool:
        ball_speed = float(np.linalg.norm(self.data.qvel[2:4]))
        if self.forward == "throw":
            return self.in_target() and ball_speed < BALL_IN_CUP_SPEED_MAX
        cup_offset = np.abs(self.data.qpos[:2] - self._centre)
        anchor_z = float(self.data.site_xpos[self._cup_site][2])
        return bool(
            np.all(cup_offset < CUP_CENTRE_TOL)
            and float(np.linalg.norm(self.data.qvel[:2])) < CUP_SPEED_MAX
            and anchor_z - float(self.ball_position()[1]) >= HANG_DROP_MIN
            and self.swing_energy() < SWING_ENERGY_MAX
        )

    def _forward_reward(self, action, before):
        in_target = float(self.in_target())
        distance = float(np.linalg.norm(self.ball_to_target()))
        reward = in_target if self.forward == "catch" else float(np.clip(distance / STRING_LENGTH, 0.0, 1.0))
        return reward, {"in_target": in_target, "distance": distance}

    def _status(self, action):
        success = self._at_initial_state()
        away = float(np.linalg.norm(self.ball_position() - self._ball_start))
        return success, 0.8 * success + 0.2 * (1.0 - float(np.clip(away / STRING_LENGTH, 0.0, 1.0))), False
