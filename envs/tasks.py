"""The task table, gymnasium registration and the torchrl factory :func:`make_env`."""
from __future__ import annotations

import difflib
from dataclasses import dataclass, field
from typing import Any

import gymnasium
import torch
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import Compose, GymWrapper, TransformedEnv
from torchrl.envs.gym_like import default_info_dict_reader

from .ball_in_cup import BallInCupEnv
from .cliff import CliffCheetahEnv, CliffWalkerEnv
from .peg import PegInsertionEnv
from .ur3 import UR3Env

__all__ = ["TaskSpec", "TASKS", "GYM_NAMESPACE", "gym_id", "make_env", "make_gym_env", "register_gym_envs", "task_spec"]

#: gymnasium namespace of the tasks' ids: ``torchrl_reset/CliffCheetah-v0`` and so on.
GYM_NAMESPACE = "torchrl_reset"
#: The tensordict entries :func:`make_env` adds from the gym ``info`` dict.
INFO_KEYS = ("reset_success", "reset_reward", "irrecoverable")


@dataclass(frozen=True)
class TaskSpec:
    """One task: its names, its gymnasium class and arguments, and the paper's numbers.

    Attributes:
        name: the task's name in recipes and :func:`make_env` (``"cliff_cheetah"``).
        gym_name: the gymnasium id without namespace (``"CliffCheetah-v0"``); None for the UR3 tasks,
            which are torchrl environments only.
        env_class: the gymnasium environment class (or, for the UR3 tasks, the torchrl one).
        kwargs: arguments for ``env_class``.
        forward_horizon: H_f, the forward episode length.
        p_thresh: the reset trigger's success-probability threshold.
        has_irrecoverable: whether the task has irrecoverable states.
        reconstructed: whether the task's definitions are ours (not from the authors' release).
        title: the task's name in tables and figures (``"cliff-cheetah"``).
        paper: the paper's Table 1 row of each algorithm (1.5M steps, mean of 5 seeds): ``{algo: (return,
            manual resets, forward share, reset success rate)}``; empty for a task the paper does not have.
        total_steps: the training length (forward and reset steps together): the paper's 1.5M, or 100k on the arm.
        curriculum: ``(index, label)``: the observation entry that Fig. 5 plots just before each triggered reset.
        exploration: the task's own exploration-noise settings over the recipe's global ``exploration.*`` (the
            release's cliff-walker noise); empty for the others.
        recipe_env: the recipe's default ``env.*`` arguments of :func:`make_env` (the UR3 tasks' backend).

    The recipes' Hydra group ``task`` is built from this table (``torchrl_reset_recipes.training.hydra_config``):
    a new task is its environment file and one entry here.
    """

    name: str
    gym_name: str | None
    env_class: type
    kwargs: dict[str, Any] = field(default_factory=dict)
    forward_horizon: int = 0
    p_thresh: float = 0.0
    has_irrecoverable: bool = False
    reconstructed: bool = False
    title: str = ""
    paper: dict[str, tuple[float, int, float, float]] = field(default_factory=dict)
    total_steps: int = 1_500_000
    curriculum: tuple[int, str] = (0, "observation[0]")
    exploration: dict[str, float] = field(default_factory=dict)
    recipe_env: dict[str, Any] = field(default_factory=dict)

    @property
    def gym_id(self) -> str | None:
        """The registered id, usable as ``gymnasium.make(f"torchrl_reset_envs:{spec.gym_id}")``."""
        return None if self.gym_name is None else f"{GYM_NAMESPACE}/{self.gym_name}"


#: the UR3 tasks' recipe defaults: the MuJoCo twin; speed_limit (rad/s) is the action bound
UR3_RECIPE_ENV = {"backend": "sim", "host": None, "speed_limit": 0.5}

TASKS: dict[str, TaskSpec] = {
    spec.name: spec
    for spec in (
        # the paper's Table 1 rows: (return, manual resets, forward share, reset success rate) per algorithm, in
        # the paper's order of tasks
        TaskSpec("ball_in_cup_catch", "BallInCupCatch-v0", BallInCupEnv, {"forward": "catch"}, 100, 0.1,
                 reconstructed=True, title="ball-in-cup (catch)",
                 paper={"lnt": (10.38, 276, 0.857, 0.993), "ours": (19.51, 331, 0.797, 0.968),
                        "lnt_sparse": (5.48, 358, 0.890, 0.975)},
                 curriculum=(2, "ball x position (m)")),
        TaskSpec("peg_insertion_insert", "PegInsertionInsert-v0", PegInsertionEnv, {"forward": "insert"}, 100, 0.1,
                 title="peg-insertion (insert)",
                 paper={"lnt": (30.50, 251, 0.717, 0.985), "ours": (29.20, 343, 0.663, 0.966),
                        "lnt_sparse": (1.60, 7175, 0.026, 0.744)},
                 curriculum=(0, "shoulder pan angle (rad)")),
        TaskSpec("cliff_cheetah", "CliffCheetah-v0", CliffCheetahEnv, {}, 500, 0.05, True, title="cliff-cheetah",
                 paper={"lnt": (4.77, 835, 0.150, 0.857), "ours": (1.96, 371, 0.314, 0.948),
                        "lnt_sparse": (2.96, 765, 0.154, 0.803)},
                 curriculum=(0, "x position (m)")),
        TaskSpec("ball_in_cup_throw", "BallInCupThrow-v0", BallInCupEnv, {"forward": "throw"}, 100, 0.1,
                 reconstructed=True, title="ball-in-cup (throw)",
                 paper={"lnt": (33.28, 359, 0.754, 0.991), "ours": (17.75, 1231, 0.479, 0.949),
                        "lnt_sparse": (31.70, 1527, 0.525, 0.878)},
                 curriculum=(2, "ball x position (m)")),
        TaskSpec("peg_insertion_remove", "PegInsertionRemove-v0", PegInsertionEnv, {"forward": "remove"}, 100, 0.1,
                 title="peg-insertion (remove)",
                 paper={"lnt": (44.57, 1714, 0.489, 0.931), "ours": (30.27, 2525, 0.326, 0.712),
                        "lnt_sparse": (0.46, 7407, 0.006, 0.353)},
                 curriculum=(0, "shoulder pan angle (rad)")),
        TaskSpec("cliff_walker", "CliffWalker-v0", CliffWalkerEnv, {}, 500, 0.05, True, title="cliff-walker",
                 paper={"lnt": (6.65, 1195, 0.057, 0.957), "ours": (6.29, 1305, 0.042, 0.687),
                        "lnt_sparse": (0.00, 1415, 0.001, 0.949)},
                 curriculum=(0, "x position (m)"),
                 exploration={"sigma": 0.01, "dt": 0.01}),  # the release's walker noise (both agents)
        # the arm: H_f = 4 s at 25 Hz; on the real arm: train.py task=ur3_peg env.backend=rtde env.host=<address>
        # (read "Before the first run on hardware" in docs/ur3.md first)
        TaskSpec("ur3_peg", None, UR3Env, {"task": "peg"}, 100, 0.1, reconstructed=True, title="UR3 peg",
                 total_steps=100_000, curriculum=(0, "cos(base joint angle)"), recipe_env=dict(UR3_RECIPE_ENV)),
        TaskSpec("ur3_reacher", None, UR3Env, {"task": "reacher"}, 100, 0.1, True, reconstructed=True,
                 title="UR3 reacher", total_steps=100_000, curriculum=(0, "cos(base joint angle)"),
                 recipe_env=dict(UR3_RECIPE_ENV)),
    )
}


class TaskInfoReader(default_info_dict_reader):
    """Copies the task flags from gym's ``info`` into tensordict entries of their spec's shape and dtype."""

    def __call__(self, info_dict: dict[str, Any], tensordict):
        for key in self.keys:
            if key not in info_dict:
                raise KeyError(f"the env's info has no {key!r} entry (got {sorted(info_dict)}).")
            spec = self.info_spec[key]
            value = torch.as_tensor(info_dict[key], dtype=spec.dtype, device=spec.device)
            tensordict.set(key, value.reshape(spec.shape))
        return tensordict


def task_spec(task: str) -> TaskSpec:
    """The :class:`TaskSpec` of ``task``, by name (``"cliff_cheetah"``) or gymnasium id; a clear error otherwise."""
    if isinstance(task, TaskSpec):
        return task
    if not isinstance(task, str):
        raise TypeError(f"task must be a task name string, got {type(task).__name__}.")
    if task in TASKS:
        return TASKS[task]
    for spec in TASKS.values():
        if spec.gym_name is not None and task in (spec.gym_name, spec.gym_id, f"torchrl_reset_envs:{spec.gym_id}"):
            return spec
    close = difflib.get_close_matches(task, list(TASKS), n=3)
    hint = f" Did you mean {' or '.join(map(repr, close))}?" if close else ""
    raise ValueError(f"unknown task {task!r}.{hint} Known tasks: {', '.join(TASKS)}.")


def gym_id(task: str) -> str:
    """The full string for ``gymnasium.make``/``GymEnv`` that needs no prior import."""
    spec = task_spec(task)
    if spec.gym_id is None:
        raise ValueError(f"{spec.name} is a torchrl environment only (no gymnasium id); use make_env({spec.name!r}).")
    return f"torchrl_reset_envs:{spec.gym_id}"


def register_gym_envs() -> None:
    """Register every task with gymnasium (done on ``import torchrl_reset_envs``; repeated calls do nothing).

    No ``max_episode_steps``: the envs never end episodes by themselves, the collector does.
    """
    for spec in TASKS.values():
        if spec.gym_id is None or spec.gym_id in gymnasium.registry:
            continue
        gymnasium.register(
            id=spec.gym_id,
            entry_point=f"{spec.env_class.__module__}:{spec.env_class.__name__}",
            kwargs=dict(spec.kwargs),
            max_episode_steps=None,
        )


def make_gym_env(task: str, **kwargs) -> gymnasium.Env:
    """The task's gymnasium environment without gymnasium's wrappers (``kwargs``: ``render_mode``, ``width``...)."""
    spec = task_spec(task)
    if spec.gym_id is None:
        raise ValueError(f"{spec.name} is a torchrl environment only (no gymnasium version); use make_env({spec.name!r}).")
    return spec.env_class(**spec.kwargs, **kwargs)


def make_env(
    task: str,
    *,
    seed: int | None = None,
    device: torch.device | str | None = None,
    render_mode: str | None = None,
    **kwargs,
) -> TransformedEnv:
    """A torchrl env of ``task``, with the at-initial-state check, the reset reward and the irrecoverable flag.

    The step and reset tensordicts carry ``observation`` (float32), ``reward``, ``reset_success``
    (bool, shape ``(1,)``), ``reset_reward`` (float32, ``(1,)``) and ``irrecoverable`` (bool, ``(1,)``).
    The returned :class:`~torchrl.envs.TransformedEnv` has an empty transform to append to, and
    ``env.task_spec``, ``env.forward_horizon`` (H_f) and ``env.p_thresh`` as metadata. Its simulator
    state is reachable through ``get_simulator_state``/``set_simulator_state`` (so
    :class:`~torchrl_reset.DualCollector` resumes exactly).

    Args:
        task (str): a name from :data:`TASKS` (``"cliff_cheetah"``, ``"cliff_walker"``,
            ``"peg_insertion_insert"``, ``"peg_insertion_remove"``, ``"ball_in_cup_catch"``,
            ``"ball_in_cup_throw"``, ``"ur3_peg"``, ``"ur3_reacher"``) or a gymnasium id.
        seed (int, optional): seeds the env's start-state noise.
        device: the tensordicts' device.
        render_mode (str, optional): ``"rgb_array"`` to allow ``env.render()`` (needs an OpenGL backend).
        **kwargs: passed to the gymnasium class (``width``, ``height``, ``camera``), or for the UR3
            tasks to :class:`~torchrl_reset_envs.UR3Env` (``backend``, ``host``, ``speed_limit``...).

    Examples:
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_reset_envs import make_env
        >>> env = make_env("peg_insertion_insert", seed=0)
        >>> check_env_specs(env)
        >>> env.forward_horizon, env.p_thresh
        (100, 0.1)
        >>> env.reset()["reset_success"]
        tensor([True])
    """
    spec = task_spec(task)
    if spec.gym_id is None:  # the UR3 tasks: a torchrl EnvBase with its own flags
        if render_mode is not None:
            raise ValueError(f"{spec.name} has no render_mode.")
        env = TransformedEnv(spec.env_class(**spec.kwargs, **kwargs, device=device), Compose())
        env.task_spec = spec
        return env
    gym_env = make_gym_env(spec, render_mode=render_mode, **kwargs)
    base = GymWrapper(gym_env, device=device)
    flag = Categorical(2, shape=(1,), dtype=torch.bool, device=base.device)
    base.set_info_dict_reader(
        TaskInfoReader(
            list(INFO_KEYS),
            spec=Composite(
                reset_success=flag.clone(),
                reset_reward=Unbounded(shape=(1,), dtype=torch.float32, device=base.device),
                irrecoverable=flag.clone(),
            ),
        )
    )
    env = TransformedEnv(base, Compose())
    env.task_spec = spec
    if seed is not None:
        env.set_seed(seed)
    return env
