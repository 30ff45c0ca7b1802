"""The recipe's agents: the paper's networks, the forward DDPG agent, the reset agent (ours: RCE on a
classifier ensemble with priors; LNT: DDPG on a Q ensemble) and the trigger each reset agent drives."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictSequential
from torch import nn
from torchrl.modules import OrnsteinUhlenbeckProcessModule, TanhModule
from torchrl.objectives import SoftUpdate

from torchrl_reset import ResetTriggerTransform, accel, bound_td0_targets

__all__ = ["speed_components", "make_actor", "with_exploration", "make_adam", "Agent", "make_forward_agent", "make_reset_agent", "make_trigger", "lnt_batch", "reset_tau"]


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
    noise = OrnsteinUhlenbeckProcessModule(
        spec=action_spec, eps_init=1.0, eps_end=1.0, annealing_num_steps=1,
        theta=cfg.exploration.theta, sigma=cfg.exploration.sigma, dt=cfg.exploration.dt,
    )
    return TensorDictSequential(actor, noise)


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


def make_forward_agent(cfg: DictConfig, obs_dim: int, action_spec, loss_class: type | None = None) -> Agent:
    """DDPG with the paper's critic layout (action joined after the first hidden layer).

    ``loss_class``: by default the accelerator's :class:`~torchrl_reset.accel.DirectDDPGLoss` (or torchrl's
    ``DDPGLoss`` with ``speed.accelerate=false``); the benchmarks pass either to compare the two."""
    parts = speed_components(cfg)
    act_dim = action_spec.shape[-1]
    actor = make_actor(obs_dim, action_spec, cfg.hidden_sizes, parts)
    critic = parts.ensemble(
        obs_dim, act_dim, num_members=1, hidden_sizes=tuple(cfg.hidden_sizes), prior_scale=0.0, out_keys=["state_action_value"]
    )
    loss = (loss_class or parts.ddpg_loss)(actor, critic, delay_actor=True, delay_value=True)
    loss.make_value_estimator(gamma=cfg.gamma)
    optimizer = make_adam(cfg, [
        {"params": list(loss.actor_network_params.values(True, True)), "lr": cfg.forward.actor_lr},
        {"params": list(loss.value_network_params.values(True, True)), "lr": cfg.forward.critic_lr},
    ])
    return Agent(actor, loss, optimizer, parts.soft_update(loss, tau=cfg.tau), critic)


def make_reset_agent(cfg: DictConfig, obs_dim: int, action_spec) -> Agent:
    """``ours``: RCE on a classifier ensemble with priors; ``lnt``/``lnt_sparse``: DDPG on a Q ensemble."""
    parts = speed_components(cfg)
    act_dim = action_spec.shape[-1]
    actor = make_actor(obs_dim, action_spec, cfg.hidden_sizes, parts)
    if cfg.algo.name == "ours":
        model = parts.ensemble(
            obs_dim, act_dim, num_members=cfg.algo.num_members, hidden_sizes=tuple(cfg.hidden_sizes),
            prior_scale=cfg.algo.prior_scale,
        )
        bias = OmegaConf.select(cfg, "algo.initial_logit_bias", default=None)
        if bias is not None:  # not the paper's: a pessimistic start, before the targets copy the networks
            with torch.no_grad():
                getattr(model, f"bias_{model.num_layers - 1}").fill_(float(bias))
        loss = parts.rce_loss(actor, model, gamma=cfg.gamma, n_steps=cfg.algo.n_steps,
                       clip_target_values=bool(OmegaConf.select(cfg, "algo.clip_target_values", default=False)))
        optimizer = make_adam(cfg, [
            {"params": list(actor.parameters()), "lr": cfg.reset.actor_lr},
            {"params": list(model.parameters()), "lr": cfg.reset.critic_lr},
        ])
    else:
        model = parts.ensemble(
            obs_dim, act_dim, num_members=cfg.algo.num_members, hidden_sizes=tuple(cfg.hidden_sizes),
            prior_scale=cfg.algo.prior_scale, out_keys=["state_action_value"],
        )
        loss = parts.ddpg_loss(actor, model, delay_actor=True, delay_value=True)
        loss.set_keys(reward="lnt_reward")
        loss.make_value_estimator(gamma=cfg.gamma)
        bounds = OmegaConf.select(cfg, "algo.reward_bounds", default=None)
        if bounds is not None:  # not the paper's: TD targets clipped to the values these rewards allow
            bound_td0_targets(loss, tuple(bounds))
        optimizer = make_adam(cfg, [
            {"params": list(loss.actor_network_params.values(True, True)), "lr": cfg.reset.actor_lr},
            {"params": list(loss.value_network_params.values(True, True)), "lr": cfg.reset.critic_lr},
        ])
    return Agent(actor, loss, optimizer, parts.soft_update(loss, tau=reset_tau(cfg)), model)


def reset_tau(cfg: DictConfig) -> float:
    """The reset agent's target rate: ``reset.tau`` where set, else the shared ``tau``."""
    tau = OmegaConf.select(cfg, "reset.tau", default=None)
    return float(cfg.tau if tau is None else tau)


def make_trigger(cfg: DictConfig, reset_agent: Agent, *, model=None, threshold=None) -> ResetTriggerTransform:
    """The reset trigger on ``reset_agent``'s model (or ``model``: a batch's runs as one, with ``threshold``
    one per row where they differ)."""
    model = reset_agent.model if model is None else model
    if cfg.algo.name == "ours":
        if threshold is None:
            threshold = float(cfg.task.p_thresh if cfg.algo.threshold is None else cfg.algo.threshold)
        return ResetTriggerTransform(model, threshold)
    return ResetTriggerTransform(
        model, float(cfg.algo.threshold) if threshold is None else threshold, score="value", reduction="min",
        model_out_key="state_action_value", score_key="reset_value",
    )


def lnt_batch(sample, algo: DictConfig, num_members: int):
    """The LNT reset agent's batch: its reward (shaped or sparse) and done flags, one column per ensemble member."""
    nxt = sample.get("next")
    reward = nxt.get("reset_reward") if algo.reset_reward == "shaped" else nxt.get("reset_success").float()
    shape = (*reward.shape[:-1], num_members)
    nxt.set("lnt_reward", reward.expand(shape))
    for key in ("done", "terminated"):
        nxt.set(key, nxt.get(key).expand(shape))
    return sample
