"""Environments for torchrl-reset, installed under the import name ``torchrl_reset_envs``.

(The folder is ``envs/`` in the repository; it is installed as ``torchrl_reset_envs`` so that it
never shadows a user project's own ``envs`` package.)

The paper's six simulated tasks are gymnasium environments, registered on import under the
``torchrl_reset`` namespace; ``gymnasium.make("torchrl_reset_envs:torchrl_reset/CliffCheetah-v0")``
imports this package first, so it needs no prior import. :func:`make_env` builds the torchrl env.
"""
from ._mujoco import MujocoResetEnv, RenderingUnavailableError, tolerance
from .ball_in_cup import BallInCupEnv
from .chain import ChainEnv
from .cliff import CliffCheetahEnv, CliffWalkerEnv
from .peg import PegInsertionEnv
from .ur3 import UR3Env
from .ur3_backends import SafetyLimits, SimBackend, SimRealtimeBackend, UR3Backend
from .ur3_rtde import RTDEBackend
from .tasks import GYM_NAMESPACE, TASKS, TaskSpec, gym_id, make_env, make_gym_env, register_gym_envs, task_spec

register_gym_envs()

__all__ = [
    "BallInCupEnv",
    "ChainEnv",
    "CliffCheetahEnv",
    "CliffWalkerEnv",
    "GYM_NAMESPACE",
    "MujocoResetEnv",
    "PegInsertionEnv",
    "RenderingUnavailableError",
    "TASKS",
    "TaskSpec",
    "RTDEBackend",
    "SafetyLimits",
    "SimBackend",
    "SimRealtimeBackend",
    "UR3Backend",
    "UR3Env",
    "gym_id",
    "make_env",
    "make_gym_env",
    "register_gym_envs",
    "task_spec",
    "tolerance",
]
