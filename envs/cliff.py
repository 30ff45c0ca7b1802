"""cliff-cheetah and cliff-walker: run forward on a floor that ends in a ditch (tasks.md)."""
from __future__ import annotations

import mujoco
import numpy as np

from ._mujoco import MujocoResetEnv, asset_path, tolerance

__all__ = ["CliffCheetahEnv", "CliffWalkerEnv"]

_TERRAIN_RGBA = (0.55, 0.6, 0.55, 1.0)
_WALL_RGBA = (0.45, 0.4, 0.35, 1.0)
_DITCH_RGBA = (0.35, 0.25, 0.2, 1.0)


def add_cliff_terrain(spec: mujoco.MjSpec, *, edge: float, far_wall: float, back_wall: float = -2.0) -> None:
    """Replace the model's infinite floor with the cliff terrain of the authors' release.

    Five boxes, 0.4 m wide in y (contype 1, conaffinity 1, the model's default contact parameters):
    the floor, top at z = 0.05 and 0.2 m thick, over ``back_wall <= x <= edge``; a wall 0.2 m thick
    centred on ``x = back_wall`` from z = 0 to 2; a 0.2 m block centred on ``x = edge`` from z = -2 to
    0 (the cliff's face); the ditch floor, top at z = -1.9, over ``edge <= x <= far_wall``; a wall
    centred on ``x = far_wall`` from z = -2 to 2. The geoms are named ``floor``, ``back_wall``,
    ``cliff_face``, ``ditch_floor`` and ``far_wall``.
    """
    spec.delete(spec.geom("floor"))
    world = spec.worldbody

    def box(name: str, x0: float, x1: float, z0: float, z1: float, rgba) -> None:
        world.add_geom(
            name=name, type=mujoco.mjtGeom.mjGEOM_BOX, pos=[(x0 + x1) / 2, 0.0, (z0 + z1) / 2],
            size=[(x1 - x0) / 2, 0.2, (z1 - z0) / 2], rgba=list(rgba), contype=1, conaffinity=1, condim=3,
        )

    box("floor", back_wall, edge, -0.15, 0.05, _TERRAIN_RGBA)
    box("back_wall", back_wall - 0.1, back_wall + 0.1, 0.0, 2.0, _WALL_RGBA)
    box("cliff_face", edge - 0.1, edge + 0.1, -2.0, 0.0, _WALL_RGBA)
    box("ditch_floor", edge, far_wall, -2.1, -1.9, _DITCH_RGBA)
    box("far_wall", far_wall - 0.1, far_wall + 0.1, -2.0, 2.0, _WALL_RGBA)


class _CliffEnv(MujocoResetEnv):
    """What the two cliff tasks share: the terrain, the task constants and the x velocity."""

    frame_skip = 5
    forward_horizon = 500
    p_thresh = 0.05
    has_irrecoverable = True
    default_camera = "track"
    model_file: str
    edge: float
    far_wall: float
    #: the height (``qpos[1]``) below which a body past the edge is in the ditch
    ditch_height: float

    def in_ditch(self, qpos) -> np.ndarray:
        """Whether each configuration ``qpos`` (``[..., nq]``) is in the ditch: past the edge and below
        ``ditch_height``, the task's irrecoverable states (one test for the env's latched flag and for
        ``recipes/analysis/recoverable.py``'s rollouts)."""
        qpos = np.asarray(qpos)
        return (qpos[..., 0] > self.edge) & (qpos[..., 1] < self.ditch_height)

    def _build_spec(self) -> mujoco.MjSpec:
        spec = mujoco.MjSpec.from_file(asset_path("gymnasium", self.model_file))
        add_cliff_terrain(spec, edge=self.edge, far_wall=self.far_wall)
        return spec

    def _velocity(self) -> float:
        """The forward velocity after the step, ``qvel[0]`` (the release reads it from the observation)."""
        return float(self.data.qvel[0])


class CliffCheetahEnv(_CliffEnv):
    """cliff-cheetah: the half-cheetah runs forward on a floor that ends in a ditch at x = 14.

    Model: gymnasium's ``half_cheetah.xml`` (timestep 0.01 s, frame skip 5, so 0.05 s per step; the
    same bodies, masses, joints and motors as the release's model) with its infinite floor replaced by
    the release's terrain (:func:`add_cliff_terrain`): floor top at z = 0.05 for -2 <= x <= 14, a wall
    at x = -2, a drop at x = 14 into a ditch whose floor (z = -1.9) ends at a wall at x = 16.

    ==================  ==========================================================================
    observation (18)    0 x (m, rootx), 1 z (m, rootz: torso height minus its start height 0.7),
                        2 pitch (rad, rooty), 3-8 joint angles bthigh, bshin, bfoot, fthigh, fshin,
                        ffoot (rad); 9-17 the same nine velocities (m/s, rad/s)
    action (6)          torques in [-1, 1] on bthigh, bshin, bfoot, fthigh, fshin, ffoot
                        (gears 120, 90, 60, 120, 60, 30)
    forward reward      ``Cond(v; 9, 11, 7)``, v = the x velocity after the step (observation 9;
                        info ``reward_velocity`` holds v)
    reset_success       ``|x| < 0.1`` and ``|pitch| < 0.1``
    reset_reward        ``clip(0.8 [|x| < 0.5] + 0.1 (1 - 0.2 |x|)
                        + 0.1 Cond(pitch; -0.05, 0.05, 0.1), 0, 1)``
    irrecoverable       ``x > 14`` and ``z < -1`` (in the ditch), latched until reset
    start state         the model's rest pose, qpos + U(-0.1, 0.1), qvel + 0.1 N(0, 1)
    H_f, p_thresh       500, 0.05
    ==================  ==========================================================================

    ``Cond`` is :func:`~torchrl_reset_envs.tolerance`. All definitions follow the authors' release.

    Examples:
        >>> from torchrl_reset_envs import CliffCheetahEnv
        >>> env = CliffCheetahEnv()
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape, sorted(k for k in info if not k.startswith("reward_"))
        ((18,), ['irrecoverable', 'reset_reward', 'reset_success'])
    """

    model_file = "half_cheetah.xml"
    edge = 14.0
    far_wall = 16.0
    ditch_height = -1.0

    def _build_spec(self) -> mujoco.MjSpec:
        spec = super()._build_spec()
        # The model scales its masses to 14 kg through the deprecated compiler attribute; do the same
        # scaling explicitly after compilation instead.
        self._total_mass = float(spec.compiler.settotalmass)
        spec.compiler.settotalmass = -1
        return spec

    def _compiled(self) -> None:
        if self._total_mass > 0:
            mujoco.mj_setTotalmass(self.model, self._total_mass)
            mujoco.mj_setConst(self.model, self.data)

    def _reset_state(self) -> None:
        rng = self.np_random
        self.data.qpos[:] = self.model.qpos0 + rng.uniform(-0.1, 0.1, size=self.model.nq)
        self.data.qvel[:] = 0.1 * rng.standard_normal(self.model.nv)

    def _observation(self) -> np.ndarray:
        return np.concatenate([self.data.qpos, self.data.qvel])

    def _forward_reward(self, action, before):
        velocity = self._velocity()
        return tolerance(velocity, 9.0, 11.0, 7.0), {"velocity": velocity}

    def _status(self, action):
        x, _, pitch = (float(v) for v in self.data.qpos[:3])
        reset_success = abs(x) < 0.1 and abs(pitch) < 0.1
        reset_reward = 0.8 * (abs(x) < 0.5) + 0.1 * (1.0 - 0.2 * abs(x)) + 0.1 * tolerance(pitch, -0.05, 0.05, 0.1)
        return reset_success, float(np.clip(reset_reward, 0.0, 1.0)), bool(self.in_ditch(self.data.qpos))


class CliffWalkerEnv(_CliffEnv):
    """cliff-walker: the 2-D walker walks forward on a floor that ends in a ditch at x = 6.

    Model: gymnasium's ``walker2d_v5.xml`` (RK4, timestep 0.002 s, frame skip 5, so 0.01 s per step)
    with the release's right-foot friction (0.9; gymnasium's v5 sets both feet to 1.9, the release only
    the left) and its infinite floor replaced by the release's terrain (:func:`add_cliff_terrain`):
    floor top at z = 0.05 for -2 <= x <= 6, a wall at x = -2, a drop at x = 6 into a ditch whose floor
    (z = -1.9) ends at a wall at x = 8. Standing at rest its feet sink about 1 cm into the floor.

    ==================  ==========================================================================
    observation (18)    0 x (m), 1 h (torso height, m), 2 pitch (rad), 3-5 right thigh, leg, foot,
                        6-8 left thigh, leg, foot angles (rad); 9-17 the nine velocities, each
                        clipped to [-10, 10]
    action (6)          torques in [-1, 1] (gear 100) on right thigh, leg, foot, left thigh, leg, foot
    forward reward      ``run * stand * upright``: ``run = clip(v / 2, 0, 1)`` (v = the x velocity
                        after the step clipped to [-10, 10], observation 9), ``stand = clip(0.25 h + 0.25 [h > 1.2]
                        + 0.5 (1 - [h < 0.7]), 0, 1)``, ``upright = Cond(pitch; -0.75, 0.75, 0.5)``
    reset_success       ``|x| < 0.5``, ``|h - 1.3| < 0.3``, ``|pitch| < 1.0``
    reset_reward        ``clip(0.8 [|x| < 0.5] + 0.2 (1 - 0.2 |x|), 0, 1) * stand * upright``
    irrecoverable       ``x > 6`` and ``h < 0`` (in the ditch), latched until reset
    start state         standing, qpos and qvel + U(-0.005, 0.005)
    H_f, p_thresh       500, 0.05
    ==================  ==========================================================================

    All definitions follow the authors' release. A walker tumbling in the ditch under full, rapidly
    switching torques can throw its torso above z = 0 for a moment without getting out (x stays above
    6); the latched flag keeps reporting the fall.

    Examples:
        >>> from torchrl_reset_envs import CliffWalkerEnv
        >>> env = CliffWalkerEnv()
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape, bool(info["reset_success"])
        ((18,), True)
    """

    model_file = "walker2d_v5.xml"
    edge = 6.0
    far_wall = 8.0
    ditch_height = 0.0

    def _build_spec(self) -> mujoco.MjSpec:
        spec = super()._build_spec()
        friction = spec.geom("foot_geom").friction
        friction[0] = 0.9  # the release's right foot (its left foot keeps 1.9)
        spec.geom("foot_geom").friction = friction
        return spec

    def _reset_state(self) -> None:
        rng = self.np_random
        self.data.qpos[:] = self.model.qpos0 + rng.uniform(-0.005, 0.005, size=self.model.nq)
        self.data.qvel[:] = rng.uniform(-0.005, 0.005, size=self.model.nv)

    def _observation(self) -> np.ndarray:
        return np.concatenate([self.data.qpos, np.clip(self.data.qvel, -10.0, 10.0)])

    def _stand_upright(self) -> tuple[float, float]:
        h, pitch = float(self.data.qpos[1]), float(self.data.qpos[2])
        stand = float(np.clip(0.25 * h + 0.25 * (h > 1.2) + 0.5 * (1.0 - (h < 0.7)), 0.0, 1.0))
        return stand, tolerance(pitch, -0.75, 0.75, 0.5)

    def _forward_reward(self, action, before):
        velocity = float(np.clip(self._velocity(), -10.0, 10.0))  # as the observation holds it
        run = float(np.clip(velocity / 2.0, 0.0, 1.0))
        stand, upright = self._stand_upright()
        return run * stand * upright, {"velocity": velocity, "run": run, "stand": stand, "upright": upright}

    def _status(self, action):
        x, h, pitch = (float(v) for v in self.data.qpos[:3])
        stand, upright = self._stand_upright()
        reset_success = abs(x) < 0.5 and abs(h - 1.3) < 0.3 and abs(pitch) < 1.0
        reset_reward = float(np.clip(0.8 * (abs(x) < 0.5) + 0.2 * (1.0 - 0.2 * abs(x)), 0.0, 1.0)) * stand * upright
        return reset_success, reset_reward, bool(self.in_ditch(self.data.qpos))
