"""One run's configuration, checked once and read everywhere as a :class:`RunSpec`.

``run_spec(cfg)`` refuses a configuration that cannot run (:func:`~.config_checks.validate`), then works out,
once, what the rest of the recipe reads: the reset agent's kind, the trigger's threshold, the horizons, the
threads, whether the run resumes, and the value of every setting that has a default for configurations
without it (:data:`DEFAULTS`). The agents, buffers, envs, collector, learner and records take the spec; none
of them looks a setting up in the raw configuration or works out the kind again.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Mapping

from omegaconf import DictConfig, OmegaConf

from torchrl_reset_recipes.training.absent_keys import DEFAULTS, FALLBACKS
from torchrl_reset_recipes.training.config_checks import reset_horizon, should_resume, validate
from torchrl_reset_recipes.training.reset_agents import KINDS, ResetAgentKind

__all__ = ["RunSpec", "run_spec", "DEFAULTS", "FALLBACKS", "reset_horizon", "torch_threads", "should_resume"]



@dataclass(frozen=True)
class RunSpec:
    """A checked configuration and what the recipe works out of it once.

    ``spec["update_order"]`` is the value of a setting of :data:`DEFAULTS` (the configuration's, or the default
    where it lacks the key); any other key is read from ``spec.cfg``.
    """

    cfg: DictConfig
    kind: ResetAgentKind
    #: the reset trigger's threshold: p_thresh for ours (a success probability), Q_thresh for LNT (a value)
    trigger_threshold: float
    forward_horizon: int  # H_f
    reset_horizon: int  # H_r
    threads: int  # torch threads of this process
    resume: bool  # continue from the run folder's newest intact checkpoint
    settings: Mapping[str, Any] = field(repr=False)

    def __getitem__(self, key: str):
        return self.settings[key]


def run_spec(cfg: DictConfig, *, check: bool = True) -> RunSpec:
    """The :class:`RunSpec` of ``cfg``, refused first (:class:`~.config_checks.ConfigError`) if it cannot run."""
    if check:
        validate(cfg)
    kind = KINDS[cfg.algo.name]
    settings = {key: _plain(OmegaConf.select(cfg, key, default=value)) for key, value in DEFAULTS.items()}
    return RunSpec(cfg=cfg, kind=kind, trigger_threshold=kind.threshold(cfg),
                   forward_horizon=int(cfg.task.forward_horizon), reset_horizon=reset_horizon(cfg),
                   threads=torch_threads(cfg), resume=should_resume(cfg), settings=MappingProxyType(settings))


def _plain(value):
    """A setting's value as plain Python (lists and mappings out of OmegaConf)."""
    if OmegaConf.is_config(value):
        return OmegaConf.to_container(value, resolve=True)
    return value


def torch_threads(cfg: DictConfig) -> int:
    """``threads``: a number, or auto: one per run in a Hydra multirun (runs go in parallel, one per
    core), else up to two."""
    if cfg.threads != "auto":
        return int(cfg.threads)
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
            return 1
    except (ImportError, ValueError):
        pass
    return max(1, min(2, os.cpu_count() or 1))
