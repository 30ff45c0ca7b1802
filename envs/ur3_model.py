"""The UR3 (CB3) arm: its DH kinematics, and a MuJoCo twin built from them for ur3-peg and ur3-reacher.

The MuJoCo model is written from the published DH parameters (ur3.md section 3), not from meshes:
each link is a chain body rotating about its z axis; the next body sits at ``(a_i, 0, d_i)``
rotated by ``alpha_i`` about x, so ``qpos`` equals the UR joint angles and the flange frame equals
the DH tool frame. Links are capsules along the DH offsets with the published link masses. The
base is mounted 0.9 m above the floor and tilted 45 degrees, pointing forward and down like a
human arm (its z axis is (sin 135°, 0, cos 135°) in the world). Joints are driven by stiff
position servos that track a ``speedj``-style velocity reference (see :class:`SimBackend`).
"""
from __future__ import annotations

import math

import mujoco
import numpy as np

__all__ = [
    "DH_A", "DH_D", "DH_ALPHA", "LINK_MASSES", "VELOCITY_LIMITS", "JOINT_LOW", "JOINT_HIGH", "BASE_POS",
    "BASE_QUAT", "HOME_Q", "PEG_LENGTH", "dh_transforms", "flange_pose", "build_ur3_spec",
]

# UR3 (CB3) DH parameters (m, rad).
DH_D = np.array([0.1519, 0.0, 0.0, 0.11235, 0.08535, 0.0819])
DH_A = np.array([0.0, -0.24365, -0.21325, 0.0, 0.0, 0.0])
DH_ALPHA = np.array([math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0])
LINK_MASSES = (2.0, 3.42, 1.26, 0.8, 0.8, 0.35)
#: hardware joint speed limits (rad/s): base, shoulder, elbow pi; wrists 2 pi
VELOCITY_LIMITS = np.array([math.pi, math.pi, math.pi, 2 * math.pi, 2 * math.pi, 2 * math.pi])
JOINT_LOW = np.array([-2 * math.pi, -2 * math.pi, -math.pi, -2 * math.pi, -2 * math.pi, -2 * math.pi])
JOINT_HIGH = -JOINT_LOW

#: the base's mounting: 0.9 m up, rotated 135 degrees about the world y axis (45 degrees below horizontal)
BASE_POS = np.array([0.0, 0.0, 0.9])
BASE_QUAT = np.array([math.cos(math.radians(135) / 2), 0.0, math.sin(math.radians(135) / 2), 0.0])
#: home joint angles: the flange points straight down, 0.4 m above the floor at (0.3, -0.2)
HOME_Q = np.array([1.4214, -1.9047, 1.3456, -1.1595, 0.7965, 0.0])
PEG_LENGTH = 0.30  # the peg runs along the flange's z axis; the floor (z = 0) serves as the table


def _x_quat(angle: float) -> list[float]:
    return [math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0]


def _quat_to_matrix(quat) -> np.ndarray:
    w, x, y, z = quat
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def dh_transforms(q) -> list[np.ndarray]:
    """The 4x4 transforms base -> frame i (i = 1..6) of the standard DH convention, in the base frame."""
    frames, t = [], np.eye(4)
    for theta, d, a, alpha in zip(np.asarray(q, dtype=np.float64), DH_D, DH_A, DH_ALPHA):
        ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
        step = np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1]])
        t = t @ step
        frames.append(t)
    return frames


def flange_pose(q, *, world: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Flange position and rotation matrix for joint angles ``q`` (world frame, or the base frame)."""
    t = dh_transforms(q)[-1]
    if not world:
        return t[:3, 3].copy(), t[:3, :3].copy()
    r_base = _quat_to_matrix(BASE_QUAT)
    return BASE_POS + r_base @ t[:3, 3], r_base @ t[:3, :3]


def build_ur3_spec(task: str, *, kp: float = 5000.0) -> mujoco.MjSpec:
    """The MuJoCo model of the UR3 for ``task`` in {"peg", "reacher"}."""
    if task not in ("peg", "reacher"):
        raise ValueError(f"task must be 'peg' or 'reacher', got {task!r}.")
    spec = mujoco.MjSpec()
    spec.modelname = f"ur3_{task}"
    spec.compiler.degree = False
    spec.option.timestep = 0.002
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.visual.global_.offwidth = 640
    spec.visual.global_.offheight = 480
    world = spec.worldbody
    world.add_light(pos=[0, 0, 3], dir=[0, 0, -1], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
    world.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[2, 2, 0.1], rgba=[0.8, 0.8, 0.75, 1])
    world.add_camera(name="side", pos=[0.45, -1.3, 0.7], xyaxes=[1, 0, 0, 0, 0.35, 0.94])
    # the stand holding the tilted base
    world.add_geom(name="stand", type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[-0.12, 0, 0, -0.12, 0, 1.05],
                   size=[0.04, 0, 0], rgba=[0.3, 0.3, 0.3, 1], contype=0, conaffinity=0)
    parent = world.add_body(name="base", pos=list(BASE_POS), quat=list(BASE_QUAT))
    parent.add_geom(type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.064, 0.03, 0], pos=[0, 0, -0.03],
                    rgba=[0.25, 0.25, 0.3, 1], contype=0, conaffinity=0)
    for i in range(6):
        if i == 0:
            body = parent.add_body(name="link1")
        else:  # frame i sits at (a_{i-1}, 0, d_{i-1}) in frame i-1, rotated by alpha_{i-1} about x
            body = parent.add_body(name=f"link{i + 1}", pos=[DH_A[i - 1], 0, DH_D[i - 1]], quat=_x_quat(DH_ALPHA[i - 1]))
        lo, hi = JOINT_LOW[i], JOINT_HIGH[i]
        body.add_joint(name=f"joint{i + 1}", axis=[0, 0, 1], range=[lo, hi], armature=0.1, damping=1.0)
        d, a = DH_D[i], DH_A[i]
        # capsules along the DH offsets (for looks and inertia), no self-collision
        pieces = [p for p in (([0, 0, 0], [0, 0, d]), ([0, 0, d], [a, 0, d])) if np.linalg.norm(np.subtract(*p)) > 1e-9]
        pieces = pieces or [([0, 0, -0.02], [0, 0, 0.02])]
        for start, end in pieces:
            body.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[*start, *end], size=[0.04 if i < 3 else 0.032, 0, 0],
                          mass=LINK_MASSES[i] / len(pieces), rgba=[0.6, 0.65, 0.7, 1], contype=0, conaffinity=0)
        act = spec.add_actuator(name=f"servo{i + 1}", target=f"joint{i + 1}", trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=kp, dampratio=1.0)
        act.ctrlrange = [lo, hi]
        act.ctrllimited = True
        parent = body
    flange = parent.add_body(name="flange", pos=[DH_A[5], 0, DH_D[5]], quat=_x_quat(DH_ALPHA[5]))
    flange.add_site(name="flange", size=[0.01, 0, 0], rgba=[1, 0, 0, 1])
    if task == "peg":
        flange.add_geom(name="peg", type=mujoco.mjtGeom.mjGEOM_CYLINDER, fromto=[0, 0, 0, 0, 0, PEG_LENGTH],
                        size=[0.01, 0, 0], mass=0.1, rgba=[0.2, 0.5, 0.9, 1], contype=1, conaffinity=1)
        flange.add_site(name="tip", pos=[0, 0, PEG_LENGTH], size=[0.008, 0, 0], rgba=[1, 0, 0, 1])
    else:
        _add_cup_and_stick(spec, flange)
    return spec


#: cup and stick of ur3-reacher (m, kg)
CUP_RADIUS = 0.018
CUP_HEIGHT = 0.06
STICK_LENGTH = 0.30
STICK_TOP_MASS = 0.1
STICK_FRICTION = 0.3


def _add_cup_and_stick(spec: mujoco.MjSpec, flange) -> None:
    """A cup opening away from the flange (upwards at home) and a top-heavy stick standing in it."""
    cup = flange.add_body(name="cup", quat=list(_flip_quat()))  # cup z = -flange z: up when the flange points down
    cup.add_geom(name="cup_floor", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[CUP_RADIUS + 0.005, 0.004, 0],
                 pos=[0, 0, 0.004], mass=0.05, rgba=[0.9, 0.9, 0.9, 1], contype=1, conaffinity=1, friction=[STICK_FRICTION, 0.005, 0.0001])
    segments = 12
    for k in range(segments):
        angle = 2 * math.pi * k / segments
        r = CUP_RADIUS + 0.004
        cup.add_geom(
            name=f"cup_wall{k}", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.004, r * math.tan(math.pi / segments) + 0.002, CUP_HEIGHT / 2],
            pos=[r * math.cos(angle), r * math.sin(angle), 0.008 + CUP_HEIGHT / 2], quat=[math.cos(angle / 2), 0, 0, math.sin(angle / 2)],
            mass=0.005, rgba=[0.9, 0.9, 0.9, 0.6], contype=1, conaffinity=1,
        )
    cup.add_site(name="cup_centre", pos=[0, 0, 0.008], size=[0.005, 0, 0])
    # The stick is a free body, so it hangs from the world: placed where the cup is at home, upright.
    p_flange, r_flange = flange_pose(HOME_Q)
    base = p_flange + r_flange @ np.array([0.0, 0.0, -0.008])
    stick = spec.worldbody.add_body(name="stick", pos=list(base))
    stick.add_freejoint(name="stick_free")
    stick.add_geom(name="stick_rod", type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[0, 0, 0.006, 0, 0, STICK_LENGTH],
                   size=[0.006, 0, 0], mass=0.01, rgba=[0.8, 0.5, 0.2, 1], contype=1, conaffinity=1, friction=[STICK_FRICTION, 0.005, 0.0001])
    stick.add_geom(name="stick_top", type=mujoco.mjtGeom.mjGEOM_SPHERE, pos=[0, 0, STICK_LENGTH], size=[0.02, 0, 0],
                   mass=STICK_TOP_MASS, rgba=[0.9, 0.2, 0.2, 1], contype=1, conaffinity=1)
    stick.add_site(name="stick_base", pos=[0, 0, 0], size=[0.004, 0, 0])
    stick.add_site(name="stick_top", pos=[0, 0, STICK_LENGTH], size=[0.004, 0, 0])


def _flip_quat() -> np.ndarray:
    """Rotation by pi about x: z -> -z."""
    return np.array([0.0, 1.0, 0.0, 0.0])
