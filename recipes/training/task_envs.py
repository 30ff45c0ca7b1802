"""The task's environments in the recipe: the training and evaluation envs with their trigger, the
real-time robot's update budget and safety counters, and the evaluation episodes (docs/method.md section 7)."""
from __future__ import annotations

from typing import Any, Callable

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from torchrl_reset_recipes.training.agents import Agent, make_trigger
from torchrl_reset_recipes.training.run_spec import RunSpec
from torchrl_reset import ResetTriggerTransform
from torchrl_reset_envs import make_env

__all__ = ["env_kwargs", "EVAL_SEED_OFFSET", "task_dimensions", "make_task_env", "UpdateBudget", "realtime_env", "safety_counters", "evaluate"]


def env_kwargs(cfg: DictConfig, *, for_eval: bool = False) -> dict:
    """``make_env`` arguments. A real arm cannot be copied: evaluation and probing then use its simulated twin."""
    env = cfg.get("env")
    kwargs = {} if env is None else dict(OmegaConf.to_container(env, resolve=True))
    if for_eval and kwargs.get("backend", "sim") != "sim":
        kwargs.update(backend="sim", host=None)
    return kwargs


#: the evaluation env is seeded ``cfg.seed + EVAL_SEED_OFFSET``, apart from the training env


EVAL_SEED_OFFSET = 10_000


def task_dimensions(cfg: DictConfig):
    """Observation size and action spec of the task (from a throw-away env)."""
    env = make_env(cfg.task.name, **env_kwargs(cfg, for_eval=True))
    out = env.observation_spec["observation"].shape[-1], env.action_spec.clone()
    env.close()
    return out


def make_task_env(spec: RunSpec, reset_agent: Agent, *, for_eval: bool = False,
                  **options) -> tuple[TransformedEnv, ResetTriggerTransform]:
    """The task's env with the reset trigger of ``reset_agent``; ``options`` go to ``make_env``
    (``render_mode``, ``width``...)."""
    cfg, trigger = spec.cfg, make_trigger(spec, reset_agent)
    env = make_env(cfg.task.name, device=cfg.device, **env_kwargs(cfg, for_eval=for_eval), **options)
    env.append_transform(trigger)
    return env, trigger


class UpdateBudget:
    """On a real-time robot, run an update only if it fits in the time left in the control period.

    Each agent's estimate is the median of its last ``window`` update durations, its first ``warmup`` updates
    left out (they carry one-time costs: allocations, the thread pool's start); ``fits(agent, time_left)`` says
    whether the estimate fits, less ``margin``. A skip lowers the estimate by ``skip_decay``, so an agent whose
    updates have become quicker is tried again in time (an update that truly does not fit is retried once in
    about ``log(fit / estimate) / log(skip_decay)`` skips). Skipped updates are counted.

    A median, not the slowest recent duration: a single slow update (the first, a collection of freed memory)
    must not stop an agent's updates for good, which the slowest-with-decay estimate did, decaying only when an
    update ran (measured on the wall-clock twin: the forward agent made 2 of its 4,000 owed updates).
    """

    def __init__(self, margin: float = 0.002, warmup: int = 2, window: int = 5, skip_decay: float = 0.999):
        self.margin, self.warmup, self.window, self.skip_decay = margin, warmup, window, skip_decay
        self.estimate: dict[str, float] = {}
        self.durations: dict[str, list[float]] = {}
        self.seen: dict[str, int] = {}
        self.skipped = 0

    def fits(self, agent: str, time_left: float) -> bool:
        if time_left - self.margin >= self.estimate.get(agent, 0.0):
            return True
        self.skipped += 1
        self.estimate[agent] *= self.skip_decay
        return False

    def record(self, agent: str, seconds: float) -> None:
        self.seen[agent] = self.seen.get(agent, 0) + 1
        if self.seen[agent] <= self.warmup:
            return
        recent = self.durations.setdefault(agent, [])
        recent.append(seconds)
        del recent[:-self.window]
        self.estimate[agent] = float(sorted(recent)[len(recent) // 2])


def realtime_env(env: TransformedEnv):
    """The innermost env if it runs in real time (the UR3 arm on the rtde backend), else None."""
    base = env
    while isinstance(base, TransformedEnv):
        base = base.base_env
    backend = getattr(base, "backend", None)
    return base if backend is not None and getattr(backend, "realtime", False) and hasattr(base, "time_left") else None


def safety_counters(env: TransformedEnv) -> dict[str, int]:
    """The robot's safety counters (protective stops, host watchdog stops...) when the env has them (UR3Env)."""
    base = env
    while isinstance(base, TransformedEnv):
        base = base.base_env
    counters = getattr(base, "safety_counters", None)
    return dict(counters()) if callable(counters) else {}


def evaluate(env: TransformedEnv, trigger: ResetTriggerTransform, forward_actor, reset_actor, *, horizon: int,
             reset_horizon: int, min_reset_steps: int, gamma: float,
             observe: Callable[[str], None] | None = None) -> dict[str, Any]:
    """One forward and one reset episode with exploration off, from ``env.reset()`` (docs/method.md section 7).

    ``observe(phase)``, when given, is called after the reset and after every step, with ``phase``
    ``"forward"``, ``"trigger"`` (the step the trigger stopped) or ``"reset"`` (recipes/analysis/video.py
    renders there).
    """
    seen = observe or (lambda phase: None)
    td = env.reset()
    seen("forward")
    ret, forward_steps, triggered = 0.0, 0, False
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        trigger.set_enabled(True)
        for t in range(horizon):
            td = env.step(forward_actor(td))
            if bool(td.get(("next", "reset_trigger")).any()):
                triggered = True
                seen("trigger")
                break
            ret += gamma**t * float(td.get(("next", "reward")))
            forward_steps += 1
            td = step_mdp(td)
            seen("forward")
        else:  # H_f steps: as in training, the next action is scored before the reset is requested
            triggered = bool(trigger.score_step(forward_actor(td.clone(False))).any())
        trigger.set_enabled(False)
        success, reset_steps = False, 0
        for t in range(reset_horizon):
            td = step_mdp(env.step(reset_actor(td)))
            reset_steps += 1
            seen("reset")
            if bool(td.get("reset_success").any()) and reset_steps >= min_reset_steps:
                success = True
                break
        trigger.set_enabled(True)
    return {"forward_return": ret, "forward_steps": forward_steps, "triggered": triggered,
            "reset_success": success, "reset_steps": reset_steps}
