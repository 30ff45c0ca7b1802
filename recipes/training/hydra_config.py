"""The recipes' Hydra configuration: ``conf/`` and the task group built from the task registry.

``task=<name>`` selects a node that :func:`register_task_configs` builds from
:data:`torchrl_reset_envs.TASKS` (H_f, p_thresh, the training length, the curriculum entry, the task's own
exploration noise and its ``env.*`` defaults), so a new task is its environment file and one registry entry;
there is no ``conf/task/`` folder to keep in step. :func:`compose` is the one way the tools, the analysis and
the tests build a configuration outside ``train.py``.
"""
from __future__ import annotations

from typing import Any, Iterable

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig

from torchrl_reset_envs import TASKS, TaskSpec
from torchrl_reset_recipes import CONF

__all__ = ["compose", "register_task_configs", "task_node"]


def task_node(spec: TaskSpec) -> dict[str, Any]:
    """The global configuration entries that ``task=<spec.name>`` sets: ``task.*`` and, for the arm, ``env.*``."""
    task: dict[str, Any] = {"name": spec.name, "forward_horizon": int(spec.forward_horizon),
                            "p_thresh": float(spec.p_thresh)}
    if spec.exploration:
        task["exploration"] = dict(spec.exploration)
    task["total_steps"] = int(spec.total_steps)
    index, label = spec.curriculum
    task["curriculum"] = {"index": int(index), "label": str(label)}
    node: dict[str, Any] = {"task": task}
    if spec.recipe_env:
        node["env"] = dict(spec.recipe_env)
    return node


def register_task_configs(tasks: dict[str, TaskSpec] | None = None) -> None:
    """Store one node per task in Hydra's config store, group ``task`` (repeated calls replace them)."""
    store = ConfigStore.instance()
    for name, spec in (TASKS if tasks is None else tasks).items():
        store.store(group="task", name=name, node=task_node(spec), package="_global_")


def compose(overrides: Iterable[str] = (), *, config_name: str = "config") -> DictConfig:
    """The configuration ``python recipes/train.py <overrides>`` runs with (without Hydra's own ``hydra.*`` node)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    register_task_configs()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return hydra_compose(config_name=config_name, overrides=list(overrides))
