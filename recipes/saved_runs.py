"""A run folder's trained agents, read back from one of its checkpoints: what the video, the probes
and anyone studying a finished run start from (the recipe itself resumes through ``run_files``)."""
from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import torch
from omegaconf import DictConfig, OmegaConf

from agents import Agent, make_forward_agent, make_reset_agent
from run_files import (MANIFEST, CheckpointDamaged, Checkpoints, checkpoint_problems, checkpoint_step,
                       identity_differences)
from task_envs import task_dimensions

__all__ = ["SavedRun", "load_agents"]

_ABSENT = object()


@dataclass
class SavedRun:
    cfg: DictConfig  # the run's config.yaml, with the overrides applied
    checkpoint: Path  # the checkpoint folder the agents were read from
    step: int  # its step (from the folder's name)
    forward: Agent | None  # None where not asked for (``agents``)
    reset: Agent | None


def load_agents(run_dir: Path | str, *, checkpoint: Path | str | None = None,
                overrides: Mapping[str, Any] | None = None,
                agents: tuple[str, ...] = ("forward", "reset")) -> SavedRun:
    """The agents of ``run_dir`` as saved in ``checkpoint`` (default: its latest complete one; also a
    kept state, ``checkpoints/kept/step_<steps>``, see ``keep_states_every``), built from the run's own
    config on the CPU. ``overrides`` set dotted config keys before the agents are built
    (``{"speed.accelerate": False}`` gives the reference ensemble, whose parts can be read apart).
    ``agents`` names the ones to build (``("reset",)`` for a probe of the reset agent alone); the others
    are None in the result. A ``checkpoint`` given (absolute, relative to the working directory, or to
    ``run_dir``) is checked as a resume checks one: a damaged one raises ``CheckpointDamaged``, another
    run's (task, algo or seed differ) ``ValueError``."""
    run_dir = Path(run_dir)
    unknown = set(agents) - {"forward", "reset"}
    if isinstance(agents, str) or unknown or not agents:
        raise ValueError(f"agents must name 'forward' and/or 'reset' (a tuple), got {agents!r}")
    config = run_dir / "config.yaml"
    if not config.exists():
        raise FileNotFoundError(f"{run_dir} holds no config.yaml: is it a run folder of recipes/train.py?")
    cfg = OmegaConf.load(config)
    if checkpoint is None:
        checkpoint = Checkpoints(run_dir / "checkpoints").latest()
        if checkpoint is None:
            raise FileNotFoundError(f"{run_dir / 'checkpoints'} holds no complete checkpoint yet.")
    else:
        checkpoint = Path(checkpoint)
        if not checkpoint.is_absolute() and not checkpoint.exists() and (run_dir / checkpoint).exists():
            checkpoint = run_dir / checkpoint  # relative to the run folder
        if checkpoint_step(checkpoint) is None or not (checkpoint / "state.pt").exists():
            raise FileNotFoundError(f"{checkpoint} is not a complete checkpoint of a run (a step_<steps> folder "
                                    "holding state.pt).")
        _check(checkpoint, run_dir, cfg)
    cfg.device = "cpu"
    for key, value in (overrides or {}).items():
        if OmegaConf.select(cfg, key, default=_ABSENT) is _ABSENT:
            raise KeyError(f"{key!r} is not a key of {config}: an override can only change a setting the run has")
        OmegaConf.update(cfg, key, value)
    obs_dim, action_spec = task_dimensions(cfg)
    state = torch.load(checkpoint / "state.pt", weights_only=False, map_location="cpu")
    forward = reset = None
    if "forward" in agents:
        forward = make_forward_agent(cfg, obs_dim, action_spec)
        forward.loss.load_state_dict(state["forward_loss"])
    if "reset" in agents:
        reset = make_reset_agent(cfg, obs_dim, action_spec)
        reset.loss.load_state_dict(state["reset_loss"])
    return SavedRun(cfg, checkpoint, checkpoint_step(checkpoint), forward, reset)


def _check(checkpoint: Path, run_dir: Path, cfg: DictConfig) -> None:
    """A checkpoint named by hand is checked as a resume checks one: its files against its manifest
    (CheckpointDamaged), and its ``meta.json`` against the run's config (ValueError for another run's)."""
    if not (checkpoint / MANIFEST).exists() and not (checkpoint / "meta.json").exists():
        warnings.warn(f"{checkpoint} holds no manifest.json or meta.json (a state kept by older code): read unverified",
                      stacklevel=3)
        return
    problems = checkpoint_problems(checkpoint)
    if problems:
        raise CheckpointDamaged(f"{checkpoint} is damaged: " + "; ".join(problems))
    differ = identity_differences(json.loads((checkpoint / "meta.json").read_text()), cfg)
    if differ:
        raise ValueError(f"{checkpoint} was saved by another run than {run_dir}: "
                         + ", ".join(f"{key} {saved!r} there, {value!r} here" for key, (saved, value) in differ.items()))
