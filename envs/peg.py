"""peg-insertion: a 7-DoF arm holding a 30 cm peg, inserting it into a hole or removing it (tasks.md)."""
from __future__ import annotations

import math

import mujoco
import numpy as np

from ._mujoco import MujocoResetEnv, asset_path

__all__ = ["PegInsertionEnv", "PEG_GOAL", "PEG_START", "INSERT_START_QPOS", "REMOVE_START_QPOS"]

#: Peg end points (bottom xyz, top xyz) with the peg fully in the hole.
PEG_GOAL = np.array([0.0, 0.3, -0.5, 0.0, 0.3, -0.2])
#: Peg end points at the insert task's start (peg above the table, clear of it).
PEG_START = np.array([0.106, 0.157, 0.150, 0.244, -0.094, 0.237])
#: Joint positions at the start of each task (no noise, zero velocity).
INSERT_START_QPOS = np.array([0.4454, 0.6419, -0.3954, -2.3214, -0.1794, -0.6032, 1.5711])
REMOVE_START_QPOS = np.array([0.5260, 0.5725, -2.0748, -1.5534, 0.1538, -0.5748, 0.7016])

_JOINTS = (
    "r_shoulder_pan_joint",
    "r_shoulder_lift_joint",
    "r_upper_arm_roll_joint",
    "r_elbow_flex_joint",
    "r_forearm_roll_joint",
    "r_wrist_flex_joint",
    "r_wrist_roll_joint",
)
_RANGES = ((-1.571, 1.715), (-0.524, 1.396), (-3.142, 0.8), (-2.321, 0.0), (-1.571, 1.571), (-2.094, 0.0), (-1.571, 1.571))

HOLE_CENTER = (0.0, 0.3)
HOLE_HALF_WIDTH_BOTTOM = 0.034  # the 6.8 cm opening at the bottom of the funnel
HOLE_HALF_WIDTH_TOP = 0.040  # the funnel's mouth, flush with the table's opening
TABLE_TOP = -0.4
PEG_RADIUS = 0.028
PEG_HALF_LENGTH = 0.15


def add_table_with_hole(spec: mujoco.MjSpec) -> None:
    """The table (top at z = -0.4, 0.4 x 0.6 m) with a square funnel-shaped hole centred at (0, 0.3).

    The funnel's walls run from z = -0.52 to -0.42, their inner faces tilted so that the opening
    narrows from 8.0 cm at the top to 6.8 cm at the bottom; the hole's floor is at z = -0.55.
    """
    world = spec.worldbody
    cx, cy = HOLE_CENTER
    a, b = HOLE_HALF_WIDTH_TOP, HOLE_HALF_WIDTH_BOTTOM
    rgba = [0.6, 0.45, 0.3, 1.0]

    def box(name, center, half, quat=(1.0, 0.0, 0.0, 0.0), color=rgba):
        world.add_geom(
            name=name, type=mujoco.mjtGeom.mjGEOM_BOX, pos=list(center), size=list(half), quat=list(quat),
            rgba=color, contype=1, conaffinity=1,
        )

    # Table slab around the opening: z from -0.42 to -0.40, x in [-0.2, 0.2], y in [0, 0.6].
    zc, hz = TABLE_TOP - 0.01, 0.01
    box("table_left", (cx - (0.2 + a) / 2, cy, zc), ((0.2 - a) / 2, 0.3, hz))
    box("table_right", (cx + (0.2 + a) / 2, cy, zc), ((0.2 - a) / 2, 0.3, hz))
    box("table_near", (cx, cy - (0.3 + a) / 2, zc), (a, (0.3 - a) / 2, hz))
    box("table_far", (cx, cy + (0.3 + a) / 2, zc), (a, (0.3 - a) / 2, hz))
    # Funnel walls from z = -0.52 to -0.42, 1 cm thick, inner face from half-width b (bottom) to a (top).
    z0, z1, thick = -0.52, -0.42, 0.01
    tilt = math.atan2(a - b, z1 - z0)
    half_height = 0.5 * math.hypot(a - b, z1 - z0)
    mid_inner, mid_z = 0.5 * (a + b), 0.5 * (z0 + z1)
    # outward normal of the +x wall's inner face, in the x-z plane
    nx, nz = math.cos(tilt), -math.sin(tilt)
    off = mid_inner + 0.5 * thick * nx
    zw = mid_z + 0.5 * thick * nz
    length = a + thick
    c, s = math.cos(tilt / 2), math.sin(tilt / 2)
    wall_color = [0.5, 0.35, 0.25, 1.0]
    box("hole_wall_px", (cx + off, cy, zw), (0.5 * thick, length, half_height), (c, 0.0, s, 0.0), wall_color)
    box("hole_wall_nx", (cx - off, cy, zw), (0.5 * thick, length, half_height), (c, 0.0, -s, 0.0), wall_color)
    box("hole_wall_py", (cx, cy + off, zw), (length, 0.5 * thick, half_height), (c, -s, 0.0, 0.0), wall_color)
    box("hole_wall_ny", (cx, cy - off, zw), (length, 0.5 * thick, half_height), (c, s, 0.0, 0.0), wall_color)
    box("hole_floor", (cx, cy, -0.56), (a + thick, a + thick, 0.01), color=wall_color)


class PegInsertionEnv(MujocoResetEnv):
    """peg-insertion: a 7-DoF arm of the PR2 type, in zero gravity, holding a 30 cm peg above a table with a hole.

    ``forward="insert"`` (peg-insertion-insert) starts with the peg above the table and rewards putting
    it into the hole; ``forward="remove"`` (peg-insertion-remove) starts with the peg in the hole and
    rewards bringing it back to the insert task's start. Each task's reset agent does the other task.

    Model: gymnasium's ``pusher_v5.xml`` arm (timestep 0.01 s, frame skip 5, so 0.05 s per step;
    armature 0.04; motors with control range [-2, 2]) with its table, object and goal removed and the
    authors' geometry applied: base at (0, -0.188, 0); joint ranges (rad) shoulder pan -1.571..1.715,
    shoulder lift -0.524..1.396, upper-arm roll -3.142..0.8, elbow flex -2.321..0, forearm roll and
    wrist roll -1.571..1.571, wrist flex -2.094..0; damping 10 on the shoulder pan (the pusher's 1.0 on
    the shoulder lift and 0.1 elsewhere); a tool frame 0.18 m beyond the wrist holding the peg (a
    cylinder of radius 0.028 along the tool's z axis from -0.15 to +0.15, ends tracked as sites
    ``bottom`` and ``top``). The table (top z = -0.4, 0.4 x 0.6 m) has a funnel-shaped square hole
    centred at (0, 0.3): walls from z = -0.52 to -0.42, opening 8.0 cm at the mouth narrowing to 6.8
    cm, floor at z = -0.55. Only the peg, the gripper and the table collide.

    With ``peg`` = (bottom xyz, top xyz), ``goal`` = ((0, 0.3, -0.5), (0, 0.3, -0.2)) and ``start`` =
    ((0.106, 0.157, 0.150), (0.244, -0.094, 0.237)): ``d_goal = |peg - goal|``, ``d_start = |peg - start|``,
    ``in_hole = d_goal < 0.1 and bottom_z < -0.45``, ``control = clip(1 - 0.1 |a|^2, 0, 1)``,
    ``insert = 0.5 in_hole + 0.25 control + 0.25 clip(1 - d_goal, 0, 1)``,
    ``remove = 0.8 clip(1 - d_start, 0, 1) + 0.2 control``.

    ==================  ==========================================================================
    observation (14)    0-6 joint angles (rad): shoulder pan, shoulder lift, upper-arm roll, elbow
                        flex, forearm roll, wrist flex, wrist roll; 7-13 their velocities (rad/s)
    action (7)          joint torques in [-2, 2], same order
    forward reward      insert: ``insert``; remove: ``remove``
    reset_success       insert: ``d_start < 0.2``; remove: ``in_hole``
    reset_reward        insert: ``remove``; remove: ``insert``
    irrecoverable       none (always False)
    start state         insert: (0.4454, 0.6419, -0.3954, -2.3214, -0.1794, -0.6032, 1.5711);
                        remove: (0.5260, 0.5725, -2.0748, -1.5534, 0.1538, -0.5748, 0.7016);
                        zero velocity, no noise
    H_f, p_thresh       100, 0.1
    ==================  ==========================================================================

    All definitions follow the authors' release; the funnel's exact wall angles are ours.

    Args:
        forward (str): ``"insert"`` or ``"remove"``.

    Examples:
        >>> from torchrl_reset_envs import PegInsertionEnv
        >>> env = PegInsertionEnv("remove")
        >>> obs, info = env.reset()
        >>> env.in_hole(), bool(info["reset_success"]), round(env.d_goal(), 3)
        (True, True, 0.0)
    """

    frame_skip = 5
    forward_horizon = 100
    p_thresh = 0.1
    default_camera = "side"

    def __init__(self, forward: str = "insert", **kwargs):
        if forward not in ("insert", "remove"):
            raise ValueError(f"forward must be 'insert' or 'remove', got {forward!r}.")
        self.forward = forward
        super().__init__(**kwargs)

    def _compiled(self) -> None:
        self._qadr = np.array([self.model.joint(name).qposadr[0] for name in _JOINTS])
        self._vadr = np.array([self.model.joint(name).dofadr[0] for name in _JOINTS])
        self._bottom = self.model.site("bottom").id
        self._top = self.model.site("top").id

    def _build_spec(self) -> mujoco.MjSpec:
        spec = mujoco.MjSpec.from_file(asset_path("gymnasium", "pusher_v5.xml"))
        spec.delete(spec.geom("table"))
        spec.delete(spec.body("object"))
        spec.delete(spec.body("goal"))
        spec.body("r_shoulder_pan_link").pos = [0.0, -0.188, 0.0]
        for name, (lo, hi) in zip(_JOINTS, _RANGES):
            spec.joint(name).range = [lo, hi]
        damping = spec.joint("r_shoulder_pan_joint").damping
        damping[0] = 10.0  # the linear damping coefficient
        spec.joint("r_shoulder_pan_joint").damping = damping
        tool = spec.body("r_wrist_roll_link").add_body(name="tool", pos=[0.18, 0.0, 0.0])
        tool.add_geom(
            name="peg", type=mujoco.mjtGeom.mjGEOM_CYLINDER, fromto=[0, 0, -PEG_HALF_LENGTH, 0, 0, PEG_HALF_LENGTH],
            size=[PEG_RADIUS, 0, 0], rgba=[0.2, 0.5, 0.9, 1.0], contype=1, conaffinity=1,
        )
        tool.add_site(name="bottom", pos=[0.0, 0.0, -PEG_HALF_LENGTH], size=[0.01, 0, 0], rgba=[1, 0, 0, 1])
        tool.add_site(name="top", pos=[0.0, 0.0, PEG_HALF_LENGTH], size=[0.01, 0, 0], rgba=[0, 1, 0, 1])
        add_table_with_hole(spec)
        spec.worldbody.add_camera(name="side", pos=[1.3, 0.25, 0.2], xyaxes=[0, 1, 0, -0.35, 0, 0.94])
        return spec

    def _reset_state(self) -> None:
        start = INSERT_START_QPOS if self.forward == "insert" else REMOVE_START_QPOS
        self.data.qpos[self._qadr] = start
        self.data.qvel[:] = 0.0

    def _observation(self) -> np.ndarray:
        return np.concatenate([self.data.qpos[self._qadr], self.data.qvel[self._vadr]])

    # ------------------------------------------------------------------ task quantities
    def peg(self) -> np.ndarray:
        """The peg's two ends, (bottom xyz, top xyz), in the world frame."""
        return np.concatenate([self.data.site_xpos[self._bottom], self.data.site_xpos[self._top]])

    def d_goal(self) -> float:
        return float(np.linalg.norm(self.peg() - PEG_GOAL))

    def d_start(self) -> float:
        return float(np.linalg.norm(self.peg() - PEG_START))

    def in_hole(self) -> bool:
        return self.d_goal() < 0.1 and float(self.data.site_xpos[self._bottom][2]) < -0.45

    def insert_reward(self, action) -> float:
        return 0.5 * self.in_hole() + 0.25 * _control(action) + 0.25 * float(np.clip(1.0 - self.d_goal(), 0.0, 1.0))

    def remove_reward(self, action) -> float:
        return 0.8 * float(np.clip(1.0 - self.d_start(), 0.0, 1.0)) + 0.2 * _control(action)

    def _forward_reward(self, action, before):
        terms = {"in_hole": float(self.in_hole()), "control": _control(action), "d_goal": self.d_goal(), "d_start": self.d_start()}
        reward = self.insert_reward(action) if self.forward == "insert" else self.remove_reward(action)
        return reward, terms

    def _status(self, action):
        if self.forward == "insert":
            return self.d_start() < 0.2, self.remove_reward(action), False
        return self.in_hole(), self.insert_reward(action), False


def _control(action) -> float:
    return float(np.clip(1.0 - 0.1 * float(np.sum(np.square(action))), 0.0, 1.0))
