"""The recipes' task group comes from the task registry: every task composes, and a new task is one entry.

Expected values come from docs/tasks.md and the authors' release (docs/method.md section 9), not from the registry.
"""
from __future__ import annotations

import dataclasses

import pytest
from hydra.core.config_store import ConfigStore
from hydra.errors import MissingConfigException
from omegaconf import OmegaConf

from torchrl_reset_envs import TASKS, CliffCheetahEnv
from torchrl_reset_recipes import CONF
from torchrl_reset_recipes.training.hydra_config import compose

from helpers import QUICK_TINY

# tasks.md: H_f and p_thresh; the paper trains 1.5M steps; the arm's runs are 100k; Fig. 5's curriculum entry:
# the x position for the cliff tasks, the ball's x position (observation entry 2) for ball-in-cup, the shoulder pan
# angle for peg
EXPECTED = {
    "cliff_cheetah": (500, 0.05, 1_500_000, 0),
    "cliff_walker": (500, 0.05, 1_500_000, 0),
    "peg_insertion_insert": (100, 0.1, 1_500_000, 0),
    "peg_insertion_remove": (100, 0.1, 1_500_000, 0),
    "ball_in_cup_catch": (100, 0.1, 1_500_000, 2),
    "ball_in_cup_throw": (100, 0.1, 1_500_000, 2),
    "ur3_peg": (100, 0.1, 100_000, 0),
    "ur3_reacher": (100, 0.1, 100_000, 0),
}


def test_every_task_composes_with_its_numbers_and_no_task_yaml_is_left():
    assert set(EXPECTED) == set(TASKS)
    assert not (CONF / "task").exists()  # one place for a task: the registry
    for name, (horizon, p_thresh, steps, index) in EXPECTED.items():
        cfg = compose([f"task={name}"])
        assert (cfg.task.name, cfg.task.forward_horizon, cfg.task.p_thresh) == (name, horizon, p_thresh)
        assert cfg.task.total_steps == steps and cfg.total_steps == steps  # total_steps follows the task's
        assert cfg.task.curriculum.index == index and cfg.task.curriculum.label


def test_the_walkers_own_noise_and_the_arms_env_defaults():
    # the release's walker noise: sigma 0.01, dt 0.01 over the global OU settings (theta stays 0.15)
    walker = compose(["task=cliff_walker"])
    assert OmegaConf.to_container(walker.task.exploration) == {"sigma": 0.01, "dt": 0.01}
    assert walker.exploration.theta == 0.15 and walker.exploration.sigma == 0.2  # the global ones, under it
    assert "exploration" not in compose(["task=cliff_cheetah"]).task
    # the arm: the MuJoCo twin unless told otherwise, 0.5 rad/s joint speeds; the others pass nothing to make_env
    arm = compose(["task=ur3_reacher"])
    assert OmegaConf.to_container(arm.env) == {"backend": "sim", "host": None, "speed_limit": 0.5}
    assert compose(["task=ur3_reacher", "env.backend=rtde", "env.host=10.0.0.2"]).env.host == "10.0.0.2"
    assert OmegaConf.to_container(compose(["task=peg_insertion_insert"]).env) == {}


def test_an_unknown_task_is_refused_with_the_known_ones():
    with pytest.raises(MissingConfigException) as refused:
        compose(["task=cliff_runner"])
    assert all(name in str(refused.value) for name in TASKS)


@pytest.fixture
def new_task(monkeypatch):
    """A task added as a user would: one registry entry (here over the cheetah's env class, with its own numbers)."""
    spec = dataclasses.replace(TASKS["cliff_cheetah"], name="cliff_sprinter", gym_name="CliffSprinter-v0",
                               title="cliff-sprinter", forward_horizon=40, p_thresh=0.2, paper={},
                               curriculum=(1, "torso height (m)"))
    monkeypatch.setitem(TASKS, spec.name, spec)
    yield spec
    ConfigStore.instance().repo["task"].pop(f"{spec.name}.yaml", None)


def test_a_new_task_is_one_registry_entry(new_task, tmp_path):
    from torchrl_reset_recipes import train

    overrides = [o for o in QUICK_TINY if not o.startswith(("task=", "task.forward_horizon="))]
    cfg = compose([*overrides, f"task={new_task.name}", f"run_dir={tmp_path}"])
    assert (cfg.task.forward_horizon, cfg.task.p_thresh, cfg.task.curriculum.index) == (40, 0.2, 1)
    assert cfg.task.total_steps == 1_500_000 and cfg.total_steps < 1_500_000  # the quick preset's length wins
    summary = train.train(cfg)
    assert summary["task"] == "cliff_sprinter" and summary["steps"] == cfg.total_steps and summary["finished"]
    assert summary["p_thresh"] == 0.2
    assert new_task.env_class is CliffCheetahEnv


def test_the_absent_key_table_names_only_settings_the_recipe_defines():
    from torchrl_reset_recipes.training.absent_keys import ABSENT_KEYS, DEFAULTS, FALLBACKS
    from torchrl_reset_recipes.training.config_checks import recipe_settings

    keys, _ = recipe_settings()
    assert set(DEFAULTS) == set(ABSENT_KEYS) | set(FALLBACKS) and not set(ABSENT_KEYS) & set(FALLBACKS)
    assert sorted(k for k in DEFAULTS if k not in keys) == []  # a renamed or dropped key cannot linger here


def test_a_configuration_without_the_release_keys_runs_as_before_them(tmp_path):
    """A config.yaml written before the release audit lacks its keys: it means the recipe's earlier behaviour
    (docs/release-audit.md: noise restarted each episode and projected onto the box, one joint step on both
    losses, transitions sampled uniformly, every target a copy), not today's release values."""
    from omegaconf import open_dict

    from torchrl_reset_recipes.training.run_spec import run_spec

    cfg = compose([f"run_dir={tmp_path}", "algo=ours"])
    today = run_spec(cfg, check=False)
    assert (today["exploration.restart"], today["update_order"], today["target_init"]) == ("never", "release", "release")
    with open_dict(cfg):
        for section, key in (("exploration", "restart"), ("exploration", "clip"), (None, "update_order"),
                             ("forward", "sampling"), (None, "target_init")):
            (cfg[section] if section else cfg).pop(key)
    old = run_spec(cfg, check=False)
    assert (old["exploration.restart"], old["exploration.clip"], old["update_order"], old["forward.sampling"],
            old["target_init"]) == ("episode", True, "joint", "transition", "copy")
