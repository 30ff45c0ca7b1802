"""The recipe's agents: the paper's networks, the forward DDPG agent, the reset agent (ours: RCE on a
classifier ensemble with priors; LNT: DDPG on a Q ensemble; each kind described in :mod:`reset_agents`)
and the trigger each reset agent drives."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from torch import nn
from torchrl.modules import OrnsteinUhlenbeckProcessModule
from torchrl.objectives import SoftUpdate

from torchrl_reset import ResetTriggerTransform, accel
from torchrl_reset.actor_heads import ActorHead, TanhHead, actor_head, head_from_settings
from torchrl_reset.stochastic_actor import EntropyDDPGLoss

from torchrl_reset_recipes.training.run_spec import RunSpec

__all__ = ["speed_components", "make_actor", "reset_head", "forward_head", "with_exploration", "exploration_settings", "make_adam", "with_temperature", "Agent", "make_forward_agent", "make_reset_agent", "make_trigger", "reset_tau"]


def speed_components(spec: RunSpec) -> accel.Components:
    """The fast classes (``speed.accelerate: true``, the default) or the plain reference ones."""
    return accel.components(bool(spec["speed.accelerate"]))


def make_actor(obs_dim: int, action_spec, hidden_sizes, parts: accel.Components | None = None,
               head: ActorHead | str = "tanh") -> TensorDictSequential:
    """The paper's policy (a 400-300 ReLU MLP, Xavier-uniform weights and zero biases) with ``head``
    (:class:`~torchrl_reset.actor_heads.ActorHead` or its name): its network on the fast path's tensor module
    where the head takes one. Every head writes the pre-activation ``action_preactivation`` beside ``action``."""
    head = actor_head(head) if isinstance(head, str) else head
    return head.make_actor(obs_dim, action_spec, tuple(hidden_sizes),
                           tensor_module=(parts or accel.components()).tensor_module)


def reset_head(spec: RunSpec) -> ActorHead:
    """The reset actor's head from ``reset.actor.*``: its kind (``head``), its penalties and, for the
    tanh-Gaussian, its temperature (``entropy: auto``, learned from 0.01 towards -dim(A); a number, fixed)."""
    return _head(spec, "reset")


def forward_head(spec: RunSpec) -> ActorHead:
    """The forward actor's head from ``forward.actor.*`` (default: the paper's deterministic tanh), read as
    :func:`reset_head` reads ``reset.actor.*``."""
    return _head(spec, "forward")


def _head(spec: RunSpec, agent: str) -> ActorHead:
    settings = {key: spec[f"{agent}.actor.{key}"] for key in ("preact_penalty", "action_l2", "entropy")}
    return head_from_settings(spec[f"{agent}.actor.head"], **settings)


def with_exploration(actor, action_spec, spec: RunSpec, head: ActorHead | None = None) -> TensorDictSequential:
    """The policy plus Ornstein-Uhlenbeck noise; ``exploration.clip: false`` (the release) leaves the noisy
    action outside the action box (the env clamps it at the motors' range; buffers and trigger see it as drawn).
    An actor whose head explores by its own samples (the tanh-Gaussian) gets no noise."""
    if head is not None and head.stochastic:
        return actor
    settings = exploration_settings(spec)
    noise = OrnsteinUhlenbeckProcessModule(
        spec=action_spec, eps_init=1.0, eps_end=1.0, annealing_num_steps=1,
        theta=settings["theta"], sigma=settings["sigma"], dt=settings["dt"],
        safe=bool(settings.get("clip", spec["exploration.clip"])),  # task.exploration.* over exploration.*
    )
    return TensorDictSequential(actor, noise)


def exploration_settings(spec: RunSpec) -> dict:
    """The noise's settings: ``exploration.*``, with the task's own ``task.exploration.*`` entries over them
    (cliff-walker's release config uses sigma 0.01 and dt 0.01)."""
    return {**OmegaConf.to_container(spec.cfg.exploration, resolve=True), **(spec["task.exploration"] or {})}


def make_adam(spec: RunSpec, groups: list[dict]) -> torch.optim.Optimizer:
    """Adam over parameter groups; with ``speed.fused_adam`` (and ``speed.accelerate``) the fused kernels
    (one pass over all parameters, the same update rule) where this torch supports them for these parameters."""
    fused = bool(spec["speed.fused_adam"]) and speed_components(spec).accelerated
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
    head: ActorHead = field(default_factory=TanhHead)  # the actor's output head: its penalties, its saturation


def make_forward_agent(spec: RunSpec, obs_dim: int, action_spec) -> Agent:
    """DDPG (torchrl's ``DDPGLoss``) with the paper's critic layout (action joined after the first hidden layer);
    with a stochastic head (``forward.actor.head: tanh_normal``) the same loss with the actor's entropy term and
    its temperature (:class:`~torchrl_reset.stochastic_actor.EntropyDDPGLoss`)."""
    cfg, parts, head = spec.cfg, speed_components(spec), forward_head(spec)
    act_dim = action_spec.shape[-1]
    actor = make_actor(obs_dim, action_spec, cfg.hidden_sizes, parts, head)
    critic = parts.ensemble(
        obs_dim, act_dim, num_members=1, hidden_sizes=tuple(cfg.hidden_sizes), prior_scale=0.0, out_keys=["state_action_value"]
    )
    if head.stochastic:
        loss = EntropyDDPGLoss(actor, critic, delay_actor=True, delay_value=True, **head.loss_kwargs())
    else:
        loss = parts.ddpg_loss(actor, critic, delay_actor=True, delay_value=True)
    loss.make_value_estimator(gamma=cfg.gamma)
    groups = [{"params": list(loss.actor_network_params.values(True, True)), "lr": cfg.forward.actor_lr},
              {"params": list(loss.value_network_params.values(True, True)), "lr": cfg.forward.critic_lr}]
    optimizer = make_adam(spec, with_temperature(groups, loss, cfg.forward.critic_lr))
    targets = parts.soft_update(loss, tau=cfg.tau)  # building it copies the networks into their targets
    if spec["target_init"] == "release":  # the target actor starts as a network of its own; the target critic as a copy
        draw_target(loss.target_actor_network_params, make_actor(obs_dim, action_spec, cfg.hidden_sizes, parts, head))
    return Agent(actor, loss, optimizer, targets, critic, head=head)


def make_reset_agent(spec: RunSpec, obs_dim: int, action_spec) -> Agent:
    """The reset agent of the run's kind (:mod:`.reset_agents`): ours, RCE on a classifier ensemble with
    priors; LNT / LNT-sparse, DDPG on a Q ensemble."""
    cfg, parts, kind = spec.cfg, speed_components(spec), spec.kind
    act_dim, head = action_spec.shape[-1], reset_head(spec)
    actor = make_actor(obs_dim, action_spec, cfg.hidden_sizes, parts, head)
    model, loss, groups = kind.build(spec, actor, obs_dim, act_dim, parts, head)
    optimizer = make_adam(spec, with_temperature(groups, loss, cfg.reset.critic_lr))
    targets = parts.soft_update(loss, tau=reset_tau(spec))  # building it copies the networks into their targets
    # the targets that start as draws of their own (target_init: release for ours; algo.target_draws for LNT)
    for network, name in kind.fresh_targets(spec, loss, obs_dim, act_dim, parts,
                                            lambda: make_actor(obs_dim, action_spec, cfg.hidden_sizes, parts, head)):
        draw_target(getattr(loss, name), network)
    return Agent(actor, loss, optimizer, targets, model, kind.critic_loss, head)


def with_temperature(groups: list[dict], loss, lr: float) -> list[dict]:
    """``groups`` plus, where ``loss`` learns its actor's temperature (a tanh-Gaussian head with ``entropy: auto``),
    a group for it at ``lr`` (the critic's rate: it steps with the actor)."""
    temperature = getattr(loss, "temperature", None)  # torchrl's DDPGLoss has none
    if temperature is None or not temperature.learned:
        return groups
    return [*groups, {"params": [temperature.log_alpha], "lr": lr}]


def draw_target(target, fresh: nn.Module) -> None:
    """Overwrites a loss's target parameters with those of ``fresh``, a newly initialised network of the same
    layout: the target then starts independent of the network it follows (what the authors' release leaves,
    whose every network constructor re-initialises all earlier variables and re-syncs only its own target).
    Entries ``fresh`` lacks (the classifiers' priors) are left shared."""
    with torch.no_grad():
        for key, value in TensorDict.from_module(fresh).items(True, True):
            target.get(key).copy_(value)


def reset_tau(spec: RunSpec) -> float:
    """The reset agent's target rate: ``reset.tau`` where set, else the shared ``tau``."""
    tau = spec["reset.tau"]
    return float(spec.cfg.tau if tau is None else tau)


def make_trigger(spec: RunSpec, reset_agent: Agent) -> ResetTriggerTransform:
    """The reset trigger on ``reset_agent``'s model, at the run's threshold (p_thresh; LNT: Q_thresh)."""
    return spec.kind.trigger(reset_agent.model, spec.trigger_threshold)
