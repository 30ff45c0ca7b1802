"""The recipe's agents: the paper's networks, the forward DDPG agent, the reset agent (ours: RCE on a
classifier ensemble with priors; LNT: DDPG on a Q ensemble; each kind described in :mod:`reset_agents`)
and the trigger each reset agent drives."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from torch import nn
from torchrl.modules import OrnsteinUhlenbeckProcessModule, TanhModule
from torchrl.objectives import SoftUpdate

from absent_keys import ABSENT_KEYS, setting
from torchrl_reset import ResetTriggerTransform, accel
from torchrl_reset.many import RowResetTriggerTransform

from reset_agents import reset_kind

__all__ = ["speed_components", "make_actor", "with_exploration", "exploration_settings", "make_adam", "Agent", "make_forward_agent", "make_reset_agent", "make_trigger", "reset_tau"]


def speed_components(cfg: DictConfig) -> accel.Components:
    """The fast classes (``speed.accelerate: true``, the default) or the plain reference ones."""
    return accel.components(bool(OmegaConf.select(cfg, "speed.accelerate", default=True)))


def make_actor(obs_dim: int, action_spec, hidden_sizes, parts: accel.Components | None = None) -> TensorDictSequential:
    """The paper's policy: a 400-300 ReLU MLP, Xavier-uniform weights and zero biases, tanh onto the action box."""
    layers, width = [], obs_dim
    for size in hidden_sizes:
        layers += [nn.Linear(width, size), nn.ReLU()]
        width = size
    layers.append(nn.Linear(width, action_spec.shape[-1]))
    net = nn.Sequential(*layers)
    for layer in net:
        if isinstance(layer, nn.Linear):
            nn.init.xavier_uniform_(layer.weight)
            nn.init.zeros_(layer.bias)
    return TensorDictSequential(
        (parts or accel.components()).tensor_module(net, "observation", "action_preactivation"),
        TanhModule(["action_preactivation"], ["action"], spec=action_spec),
    )


def with_exploration(actor, action_spec, cfg: DictConfig) -> TensorDictSequential:
    """The policy plus Ornstein-Uhlenbeck noise; ``exploration.clip: false`` (the release) leaves the noisy
    action outside the action box (the env clamps it at the motors' range; buffers and trigger see it as drawn)."""
    settings = exploration_settings(cfg)
    noise = OrnsteinUhlenbeckProcessModule(
        spec=action_spec, eps_init=1.0, eps_end=1.0, annealing_num_steps=1,
        theta=settings["theta"], sigma=settings["sigma"], dt=settings["dt"],
        safe=bool(settings.get("clip", ABSENT_KEYS["exploration.clip"])),  # task.exploration.* over exploration.*
    )
    return TensorDictSequential(actor, noise)


def exploration_settings(cfg: DictConfig) -> dict:
    """The noise's settings: ``exploration.*``, with the task's own ``task.exploration.*`` entries over them
    (cliff-walker's release config uses sigma 0.01 and dt 0.01)."""
    task = OmegaConf.select(cfg, "task.exploration", default=None)
    own = {} if task is None else OmegaConf.to_container(task, resolve=True)
    return {**OmegaConf.to_container(cfg.exploration, resolve=True), **own}


def make_adam(cfg: DictConfig, groups: list[dict]) -> torch.optim.Optimizer:
    """Adam over parameter groups; with ``speed.fused_adam`` (and ``speed.accelerate``) the fused kernels
    (one pass over all parameters, the same update rule) where this torch supports them for these parameters."""
    fused = bool(OmegaConf.select(cfg, "speed.fused_adam", default=False)) and speed_components(cfg).accelerated
    if fused:
        try:
            return torch.optim.Adam(groups, fused=True)
        except (RuntimeError, ValueError):  # a device or dtype without fused kernels
            pass
    return torch.optim.Adam(groups)


@dataclass
class Agent:
    """One agent: its policy, loss module, optimizer and target updater."""

    actor: TensorDictSequential
    loss: Any
    optimizer: torch.optim.Optimizer
    targets: SoftUpdate
    model: Any  # the critic or classifier ensemble
    critic_loss: str = "loss_value"  # its critic's loss entry, minimised beside "loss_actor" ("loss_classifier": RCE)


def make_forward_agent(cfg: DictConfig, obs_dim: int, action_spec) -> Agent:
    """DDPG (torchrl's ``DDPGLoss``) with the paper's critic layout (action joined after the first hidden layer)."""
    parts = speed_components(cfg)
    act_dim = action_spec.shape[-1]
    actor = make_actor(obs_dim, action_spec, cfg.hidden_sizes, parts)
    critic = parts.ensemble(
        obs_dim, act_dim, num_members=1, hidden_sizes=tuple(cfg.hidden_sizes), prior_scale=0.0, out_keys=["state_action_value"]
    )
    loss = parts.ddpg_loss(actor, critic, delay_actor=True, delay_value=True)
    loss.make_value_estimator(gamma=cfg.gamma)
    optimizer = make_adam(cfg, [
        {"params": list(loss.actor_network_params.values(True, True)), "lr": cfg.forward.actor_lr},
        {"params": list(loss.value_network_params.values(True, True)), "lr": cfg.forward.critic_lr},
    ])
    targets = parts.soft_update(loss, tau=cfg.tau)  # building it copies the networks into their targets
    if releases_targets(cfg):  # the target actor starts as a network of its own; the target critic as a copy
        draw_target(loss.target_actor_network_params, make_actor(obs_dim, action_spec, cfg.hidden_sizes, parts))
    return Agent(actor, loss, optimizer, targets, critic)


def make_reset_agent(cfg: DictConfig, obs_dim: int, action_spec) -> Agent:
    """The reset agent of ``cfg.algo.name`` (:mod:`reset_agents`): ours, RCE on a classifier ensemble with
    priors; LNT / LNT-sparse, DDPG on a Q ensemble."""
    parts, kind = speed_components(cfg), reset_kind(cfg)
    act_dim = action_spec.shape[-1]
    actor = make_actor(obs_dim, action_spec, cfg.hidden_sizes, parts)
    model, loss, groups = kind.build(cfg, actor, obs_dim, act_dim, parts)
    optimizer = make_adam(cfg, groups)
    targets = parts.soft_update(loss, tau=reset_tau(cfg))  # building it copies the networks into their targets
    fresh = kind.fresh_target(cfg, obs_dim, act_dim, parts) if releases_targets(cfg) else None
    if fresh is not None:  # target_init: release
        network, name = fresh
        draw_target(getattr(loss, name), network)
    return Agent(actor, loss, optimizer, targets, model, kind.critic_loss)


def releases_targets(cfg: DictConfig) -> bool:
    """``target_init: release``: the targets the release's network constructors leave (configs without the key: copies)."""
    return setting(cfg, "target_init") == "release"


def draw_target(target, fresh: nn.Module) -> None:
    """Overwrites a loss's target parameters with those of ``fresh``, a newly initialised network of the same
    layout: the target then starts independent of the network it follows (what the authors' release leaves,
    whose every network constructor re-initialises all earlier variables and re-syncs only its own target).
    Entries ``fresh`` lacks (the classifiers' priors) are left shared."""
    with torch.no_grad():
        for key, value in TensorDict.from_module(fresh).items(True, True):
            target.get(key).copy_(value)


def reset_tau(cfg: DictConfig) -> float:
    """The reset agent's target rate: ``reset.tau`` where set, else the shared ``tau``."""
    tau = OmegaConf.select(cfg, "reset.tau", default=None)
    return float(cfg.tau if tau is None else tau)


def make_trigger(cfg: DictConfig, reset_agent: Agent, *, model=None, threshold=None,
                 rows: bool = False) -> ResetTriggerTransform:
    """The reset trigger on ``reset_agent``'s model (or ``model``: a batch's runs as one, with ``threshold``
    one per row where they differ). ``rows``: the trigger of an env of N copies each in its own phase
    (:class:`~torchrl_reset.many.RowResetTriggerTransform`, for ``arms=`` and a batch's batched acting)."""
    kind = reset_kind(cfg)
    return kind.trigger(reset_agent.model if model is None else model,
                        kind.threshold(cfg) if threshold is None else threshold,
                        RowResetTriggerTransform if rows else ResetTriggerTransform)
