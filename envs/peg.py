"""peg-insertion: a 7-DoF arm holding a 30 cm peg, inserting it into a hole or removing it (tasks.md)."""
from __future__ import annotations

import math

import mujoco
import numpy as np

from ._mujoco import MujocoResetEnv

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
_RANGES = ((-1.571, 1.714602), (-0.5236, 1.3963), (-3.1416, 0.8), (-2.3213, 0.0), (-1.571, 1.571), (-2.094, 0.0), (-1.571, 1.571))

PEG_RADIUS = 0.028
PEG_HALF_LENGTH = 0.15

# -------------------------------------------------------------------------------- the model
# The arm, the peg and the table with its hole, written out from the physical parameters of the
# authors' release (docs/method.md section 9; docs/release-audit.md lists each number).
TIMESTEP = 0.01
SOLVER_ITERATIONS = 20
JOINT_ARMATURE = 0.04
DEFAULT_DAMPING = 1.0
GEOM_FRICTION = (0.5, 0.1, 0.1)
GEOM_MARGIN = 0.002
DEFAULT_DENSITY = 1000.0
PEG_DENSITY = 2000.0
MOTOR_RANGE = 2.0  # the motors' control range (N m); the policy's actions in [-1, 1] use half of it

#: (joint, axis, damping) in chain order; ranges in ``_RANGES``.
_JOINT_AXES = ((0, 0, 1), (0, 1, 0), (1, 0, 0), (0, 1, 0), (1, 0, 0), (0, 1, 0), (1, 0, 0))
_DAMPING = (10.0, 10.0, 0.1, 1.0, 0.1, 0.1, 0.1)
#: Each joint's link: the link's origin in its parent's frame and its capsules (from, to, radius).
_LINKS = (
    ((0.0, -0.188, 0.0), (((0, 0, -0.4), (0, 0, 0.2), 0.1),)),          # shoulder pan: the torso column
    ((0.1, 0.0, 0.0), (((0, -0.1, 0), (0, 0.1, 0), 0.1),)),             # shoulder lift
    ((0.0, 0.0, 0.0), (((-0.1, 0, 0), (0.1, 0, 0), 0.02), ((0, 0, 0), (0.4, 0, 0), 0.06))),  # upper-arm roll + upper arm
    ((0.4, 0.0, 0.0), (((0, -0.02, 0), (0, 0.02, 0), 0.06),)),          # elbow flex
    ((0.0, 0.0, 0.0), (((-0.1, 0, 0), (0.1, 0, 0), 0.02), ((0, 0, 0), (0.321, 0, 0), 0.05))),  # forearm roll + forearm
    ((0.321, 0.0, 0.0), (((0, -0.02, 0), (0, 0.02, 0), 0.01),)),        # wrist flex
    ((0.0, 0.0, 0.0), (((-0.02, 0, 0), (0.02, 0, 0), 0.01), ((0.05, 0, -0.02), (0.05, 0, 0.02), 0.05))),  # wrist roll + palm
)
#: Two spheres on the torso column (radius 0.05 and 0.03), part of the shoulder-pan link's mass.
_HEAD_SPHERES = (((-0.06, 0.05, 0.2), 0.05), ((0.06, 0.05, 0.2), 0.05), ((-0.06, 0.09, 0.2), 0.03), ((0.06, 0.09, 0.2), 0.03))
#: The gripper's two fingers in the palm's frame: (base, first segment's end, tip segment's end), radius 0.01.
_FINGERS = (
    ((0.07691, 0.03, 0.0), (0.09137, 0.00495, 0.0), (0.09137, 0.0, 0.0)),
    ((0.07691, -0.03, 0.0), (0.09137, -0.00495, 0.0), (0.09137, 0.0, 0.0)),
)
TOOL_OFFSET = 0.18  # the tool frame (the peg's centre) along the palm's x axis

#: The hole's four walls: centre, half sizes, rotation (axis, angle in rad); 1 cm x 2 cm x 10 cm plates
#: leaning 0.05 rad outwards, their inner faces 6.2 cm apart at the bottom.
_HOLE_WALLS = (
    ((0.034, 0.3, -0.47), (0.003, 0.01, 0.05), ((0, 1, 0), 0.05)),
    ((-0.034, 0.3, -0.47), (0.003, 0.01, 0.05), ((0, 1, 0), -0.05)),
    ((0.0, 0.334, -0.47), (0.01, 0.003, 0.05), ((1, 0, 0), -0.05)),
    ((0.0, 0.266, -0.47), (0.01, 0.003, 0.05), ((1, 0, 0), 0.05)),
)
#: The hole's floor and the table's four slabs (top at z = -0.4) around a 6.6 cm square opening.
_TABLE = (
    ((0.0, 0.3, -0.55), (0.2, 0.2, 0.05)),
    ((0.216, 0.3, -0.45), (0.183, 0.3, 0.05)),
    ((-0.216, 0.3, -0.45), (0.183, 0.3, 0.05)),
    ((0.0, 0.516, -0.45), (0.032, 0.183, 0.05)),
    ((0.0, 0.084, -0.45), (0.032, 0.183, 0.05)),
)


def _quat(axis, angle: float) -> list[float]:
    half = 0.5 * angle
    return [math.cos(half), *(math.sin(half) * np.asarray(axis, dtype=float))]


def build_peg_spec() -> mujoco.MjSpec:
    """The peg-insertion model (both tasks), built from the numbers above.

    Zero gravity, RK4 at 0.01 s, 20 solver iterations. Joints: armature 0.04, limited, damping per
    ``_DAMPING``. Geoms: density 1000 unless stated, friction (0.5, 0.1, 0.1), margin 2 mm, condim 1;
    the arm's geoms (contype 0, conaffinity 1) touch the table and hole (contype 1, conaffinity 1) but
    not each other or the peg; the peg (contype 2, conaffinity 1, density 2000) touches the table and
    hole. Seven motors on the joints, control range +-2.
    """
    spec = mujoco.MjSpec()
    spec.modelname = "peg_insertion"
    spec.compiler.degree = False
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE
    spec.option.timestep = TIMESTEP
    spec.option.gravity = [0.0, 0.0, 0.0]
    spec.option.iterations = SOLVER_ITERATIONS
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_RK4
    defaults = spec.default
    defaults.joint.armature = JOINT_ARMATURE
    defaults.joint.damping = [DEFAULT_DAMPING, 0.0, 0.0]  # linear damping (this MuJoCo's higher terms zero)
    defaults.joint.limited = mujoco.mjtLimited.mjLIMITED_TRUE
    defaults.geom.friction = list(GEOM_FRICTION)
    defaults.geom.margin = GEOM_MARGIN
    defaults.geom.condim = 1
    defaults.geom.contype = 0
    defaults.geom.conaffinity = 1
    defaults.geom.density = DEFAULT_DENSITY
    capsule, sphere = mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_SPHERE
    grey = [0.6, 0.6, 0.6, 1.0]

    world = spec.worldbody
    world.add_light(pos=[0, 0, 3], dir=[0, 0, -1], diffuse=[0.5, 0.5, 0.5])
    body = world
    for name, axis, (lo, hi), damping, (pos, capsules) in zip(_JOINTS, _JOINT_AXES, _RANGES, _DAMPING, _LINKS):
        body = body.add_body(name=name.replace("_joint", "_link"), pos=list(pos))
        body.add_joint(name=name, type=mujoco.mjtJoint.mjJNT_HINGE, axis=list(axis), range=[lo, hi], damping=[damping, 0.0, 0.0])
        for a, b, radius in capsules:
            body.add_geom(type=capsule, fromto=[*a, *b], size=[radius, 0, 0], rgba=grey)
        if name == "r_shoulder_pan_joint":
            for centre, radius in _HEAD_SPHERES:
                body.add_geom(type=sphere, pos=list(centre), size=[radius, 0, 0], rgba=[0.3, 0.3, 0.3, 1.0])
    palm = body
    for base, first, tip in _FINGERS:
        finger = palm.add_body(pos=list(base))
        finger.add_geom(type=capsule, fromto=[0, 0, 0, *first], size=[0.01, 0, 0], rgba=grey)
        finger.add_body(pos=list(first)).add_geom(type=capsule, fromto=[0, 0, 0, *tip], size=[0.01, 0, 0], rgba=grey)
    tool = palm.add_body(name="tool", pos=[TOOL_OFFSET, 0.0, 0.0])
    tool.add_geom(
        name="peg", type=mujoco.mjtGeom.mjGEOM_CYLINDER, fromto=[0, 0, -PEG_HALF_LENGTH, 0, 0, PEG_HALF_LENGTH],
        size=[PEG_RADIUS, 0, 0], density=PEG_DENSITY, contype=2, conaffinity=1, rgba=[0.2, 0.5, 0.9, 1.0],
    )
    for end, z, rgba in (("bottom", -PEG_HALF_LENGTH, [1, 0, 0, 1]), ("top", PEG_HALF_LENGTH, [0, 1, 0, 1])):
        # the peg's ends: spheres of the peg's radius (they touch the table like the arm's geoms)
        tool.add_geom(name=f"peg_{end}", type=sphere, pos=[0.0, 0.0, z], size=[PEG_RADIUS, 0, 0], rgba=rgba)
        tool.add_site(name=end, pos=[0.0, 0.0, z], size=[0.01, 0, 0], rgba=rgba)

    box = mujoco.mjtGeom.mjGEOM_BOX
    for i, (centre, half, (axis, angle)) in enumerate(_HOLE_WALLS):
        world.add_geom(name=f"hole_wall{i}", type=box, pos=list(centre), size=list(half), quat=_quat(axis, angle),
                       contype=1, conaffinity=1, rgba=[0.7, 0.7, 0.7, 1.0])
    for i, (centre, half) in enumerate(_TABLE):
        world.add_geom(name="hole_floor" if i == 0 else f"table{i}", type=box, pos=list(centre), size=list(half),
                       contype=1, conaffinity=1, rgba=[0.5, 0.5, 0.5, 1.0] if i == 0 else [0.6, 0.6, 0.6, 1.0])
    for name in _JOINTS:
        spec.add_actuator(
            name=name.replace("_joint", "_motor"), target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT,
            ctrllimited=mujoco.mjtLimited.mjLIMITED_TRUE, ctrlrange=[-MOTOR_RANGE, MOTOR_RANGE],
        )
    world.add_camera(name="side", pos=[1.3, 0.25, 0.2], xyaxes=[0, 1, 0, -0.35, 0, 0.94])
    return spec


class PegInsertionEnv(MujocoResetEnv):
    """peg-insertion: a 7-DoF arm of the PR2 type, in zero gravity, holding a 30 cm peg above a table with a hole.

    ``forward="insert"`` (peg-insertion-insert) starts with the peg above the table and rewards putting
    it into the hole; ``forward="remove"`` (peg-insertion-remove) starts with the peg in the hole and
    rewards bringing it back to the insert task's start. Each task's reset agent does the other task.

    Model (:func:`build_peg_spec`, written from the physical parameters of the authors' release):
    zero gravity, RK4 at 0.01 s, frame skip 5 (0.05 s per step), 20 solver iterations; joints with
    armature 0.04 and damping 10 (shoulder pan and lift), 1 (elbow flex) and 0.1 (the rolls and the
    wrist flex); capsule links at density 1000 (arm 46.2 kg); a tool frame 0.18 m beyond the wrist
    holding the peg, a cylinder of radius 0.028 from -0.15 to +0.15 along the tool's z axis at density
    2000 with a sphere of its radius at each end (1.66 kg; the ends tracked as sites ``bottom`` and
    ``top``); motors with control range [-2, 2] of which the actions use [-1, 1] (the release sends its
    actor's tanh output unscaled). The table's top is at z = -0.4 around a 6.6 cm square opening
    centred at (0, 0.3), with four 1 cm wall plates leaning 0.05 rad outwards from z = -0.52 to -0.42
    and the hole's floor at z = -0.5. The arm's geoms touch the table but not each other or the peg;
    the peg touches the table. At the remove task's start (the release's joint angles) the peg's
    bottom sphere lies 2.8 cm inside the hole's floor and the palm 2 cm inside the table, as in the
    release's model: the contacts push the peg up and out of the hole within about four steps if
    nothing holds it.

    With ``peg`` = (bottom xyz, top xyz), ``goal`` = ((0, 0.3, -0.5), (0, 0.3, -0.2)) and ``start`` =
    ((0.106, 0.157, 0.150), (0.244, -0.094, 0.237)): ``d_goal = |peg - goal|``, ``d_start = |peg - start|``,
    ``in_hole = d_goal < 0.1 and bottom_z < -0.45``, ``control = clip(1 - 0.1 |a|^2, 0, 1)``,
    ``insert = 0.5 in_hole + 0.25 control + 0.25 clip(1 - d_goal, 0, 1)``,
    ``remove = 0.8 clip(1 - d_start, 0, 1) + 0.2 control``.

    ==================  ==========================================================================
    observation (14)    0-6 joint angles (rad): shoulder pan, shoulder lift, upper-arm roll, elbow
                        flex, forearm roll, wrist flex, wrist roll; 7-13 their velocities (rad/s)
    action (7)          joint torques in [-1, 1] (N m), same order, sent unscaled
    forward reward      insert: ``insert``; remove: ``remove``
    reset_success       insert: ``d_start < 0.2``; remove: ``in_hole``
    reset_reward        insert: ``remove``; remove: ``insert``
    irrecoverable       none (always False)
    start state         insert: (0.4454, 0.6419, -0.3954, -2.3214, -0.1794, -0.6032, 1.5711);
                        remove: (0.5260, 0.5725, -2.0748, -1.5534, 0.1538, -0.5748, 0.7016);
                        zero velocity, no noise
    H_f, p_thresh       100, 0.1
    ==================  ==========================================================================

    All definitions follow the authors' release (docs/release-audit.md).

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
    action_bound = 1.0
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
        return build_peg_spec()

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
