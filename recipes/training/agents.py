"""The recipe's agents: the paper's networks, the forward DDPG agent, the reset agent (ours: RCE on a
classifier ensemble with priors; LNT: DDPG on a Q ensemble; each kind described in :mod:`reset_agents`)
and the trigger each reset agent drives."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import OrnsteinUhlenbeckProcessModule, ProbabilisticActor, TanhModule, TanhNormal
from torchrl.objectives import SoftUpdate

from torchrl_reset import ResetTriggerTransform, accel
from torchrl_reset.actor_heads import EntropyBonus, InvertingGradientHead, actor_penalties

from torchrl_reset_recipes.training.run_spec import RunSpec

__all__ = ["ACTOR_HEADS", "speed_components", "make_actor", "normalised_action", "ActorTerms", "make_actor_terms", "with_exploration", "exploration_settings", "make_adam", "Agent", "make_forward_agent", "make_reset_agent", "make_trigger", "reset_tau"]


def speed_components(spec: RunSpec) -> accel.Components:
    """The fast classes (``speed.accelerate: true``, the default) or the plain reference ones."""
    return accel.components(bool(spec["speed.accelerate"]))


#: the reset actor's output heads (``reset.actor.head``): the release's deterministic tanh, the linear output with
#: inverted gradients at the bounds, the stochastic tanh-Gaussian (RCE's original actor)
ACTOR_HEADS = ("tanh", "inverting", "tanh_normal")


def make_actor(obs_dim: int, action_spec, hidden_sizes, parts: accel.Components | None = None,
               head: str = "tanh") -> TensorDictSequential:
    """The paper's policy: a 400-300 ReLU MLP, Xavier-uniform weights and zero biases, onto the action box by
    ``head`` (:data:`ACTOR_HEADS`): ``tanh`` (the paper's), ``inverting`` (a linear output clipped to the box,
    :class:`~torchrl_reset.actor_heads.InvertingGradientHead`) or ``tanh_normal`` (a torchrl
    ``ProbabilisticActor`` on a ``TanhNormal`` whose location is the pre-activation: it samples in
    ``ExplorationType.RANDOM``, the collector's mode, and acts ``tanh(loc)`` otherwise). Every head writes the
    pre-activation ``action_preactivation`` beside ``action``."""
    if head not in ACTOR_HEADS:
        raise ValueError(f"unknown actor head {head!r}; known: {', '.join(ACTOR_HEADS)}")
    act_dim = action_spec.shape[-1]
    layers, width = [], obs_dim
    for size in hidden_sizes:
        layers += [nn.Linear(width, size), nn.ReLU()]
        width = size
    layers.append(nn.Linear(width, 2 * act_dim if head == "tanh_normal" else act_dim))
    net = nn.Sequential(*layers)
    for layer in net:
        if isinstance(layer, nn.Linear):
            nn.init.xavier_uniform_(layer.weight)
            nn.init.zeros_(layer.bias)
    if head == "tanh_normal":
        module = TensorDictModule(nn.Sequential(net, NormalParamExtractor()), in_keys=["observation"],
                                  out_keys=["action_preactivation", "action_scale"])
        low, high = action_spec.space.low, action_spec.space.high
        return TensorDictSequential(ProbabilisticActor(
            module, in_keys={"loc": "action_preactivation", "scale": "action_scale"}, spec=action_spec,
            distribution_class=TanhNormal, distribution_kwargs={"low": low, "high": high}, return_log_prob=True))
    squash = (TanhModule(["action_preactivation"], ["action"], spec=action_spec) if head == "tanh"
              else InvertingGradientHead(action_spec.space.low, action_spec.space.high))
    return TensorDictSequential((parts or accel.components()).tensor_module(net, "observation", "action_preactivation"),
                                squash)


def normalised_action(preactivation: torch.Tensor, head: str) -> torch.Tensor:
    """The policy's noiseless action in the box's normalised coordinates ([-1, 1]) from its pre-activation."""
    return preactivation.clamp(-1.0, 1.0) if head == "inverting" else torch.tanh(preactivation)


class ActorTerms:
    """What ``reset.actor`` adds to the reset actor's loss, on the states of the actor's batch: the penalties
    (``preact_penalty`` on ``mean(u^2)``, ``action_l2`` on the normalised action's ``mean(a^2)``) and, for the
    ``tanh_normal`` head, the entropy term (:class:`~torchrl_reset.actor_heads.EntropyBonus`, whose learned
    temperature, when ``entropy: auto``, is a parameter of the reset loss and of its optimizer). The terms take
    an actor pass of their own on those states (for the entropy, a sample of its own: an unbiased estimate of
    ``E[alpha log pi]`` beside the loss's own sampled actions)."""

    def __init__(self, actor, head: str, preact_penalty: float, action_l2: float, entropy: EntropyBonus | None):
        self.actor, self.head = actor, head
        self.preact_penalty, self.action_l2, self.entropy = preact_penalty, action_l2, entropy

    @property
    def stochastic(self) -> bool:
        """Whether the actor's loss takes sampled actions (the tanh-Gaussian head)."""
        return self.head == "tanh_normal"

    def __call__(self, sample) -> torch.Tensor:
        with set_exploration_type(ExplorationType.RANDOM if self.stochastic else ExplorationType.DETERMINISTIC):
            td = self.actor(sample.select(*self.actor.in_keys))
        u = td.get("action_preactivation")
        total = actor_penalties(u, normalised_action(u, self.head), preact_penalty=self.preact_penalty,
                                action_l2=self.action_l2)
        if self.entropy is not None:
            total = total + self.entropy(td.get("action_log_prob"))
        return total


def make_actor_terms(spec: RunSpec, actor, action_dim: int) -> ActorTerms | None:
    """The terms ``reset.actor`` adds to the reset actor's loss, or None where it adds none (the release)."""
    head = spec["reset.actor.head"]
    preact, l2 = float(spec["reset.actor.preact_penalty"]), float(spec["reset.actor.action_l2"])
    entropy = spec["reset.actor.entropy"]
    bonus = None
    if head == "tanh_normal":
        bonus = (EntropyBonus(AUTO_ENTROPY_INIT, target_entropy=-float(action_dim)) if entropy == "auto"
                 else EntropyBonus(float(entropy)))
    if head != "tanh_normal" and not preact and not l2:
        return None
    return ActorTerms(actor, head, preact, l2, bonus)


#: ``reset.actor.entropy: auto``: the temperature's first value (RCE's fixed coefficient is 1e-4; SAC starts at
#: 1 for rewards whose values run to the hundreds, where this actor's objective, a probability, stays below 1)
AUTO_ENTROPY_INIT = 0.01


def with_exploration(actor, action_spec, spec: RunSpec, head: str = "tanh") -> TensorDictSequential:
    """The policy plus Ornstein-Uhlenbeck noise; ``exploration.clip: false`` (the release) leaves the noisy
    action outside the action box (the env clamps it at the motors' range; buffers and trigger see it as drawn).
    A ``tanh_normal`` actor explores by its own samples and gets no noise."""
    if head == "tanh_normal":
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
    actor_terms: ActorTerms | None = None  # what reset.actor adds to the actor's loss (None: nothing)
    head: str = "tanh"  # the actor's output head (ACTOR_HEADS)


def make_forward_agent(spec: RunSpec, obs_dim: int, action_spec) -> Agent:
    """DDPG (torchrl's ``DDPGLoss``) with the paper's critic layout (action joined after the first hidden layer)."""
    cfg, parts = spec.cfg, speed_components(spec)
    act_dim = action_spec.shape[-1]
    actor = make_actor(obs_dim, action_spec, cfg.hidden_sizes, parts)
    critic = parts.ensemble(
        obs_dim, act_dim, num_members=1, hidden_sizes=tuple(cfg.hidden_sizes), prior_scale=0.0, out_keys=["state_action_value"]
    )
    loss = parts.ddpg_loss(actor, critic, delay_actor=True, delay_value=True)
    loss.make_value_estimator(gamma=cfg.gamma)
    optimizer = make_adam(spec, [
        {"params": list(loss.actor_network_params.values(True, True)), "lr": cfg.forward.actor_lr},
        {"params": list(loss.value_network_params.values(True, True)), "lr": cfg.forward.critic_lr},
    ])
    targets = parts.soft_update(loss, tau=cfg.tau)  # building it copies the networks into their targets
    if spec["target_init"] == "release":  # the target actor starts as a network of its own; the target critic as a copy
        draw_target(loss.target_actor_network_params, make_actor(obs_dim, action_spec, cfg.hidden_sizes, parts))
    return Agent(actor, loss, optimizer, targets, critic)


def make_reset_agent(spec: RunSpec, obs_dim: int, action_spec) -> Agent:
    """The reset agent of the run's kind (:mod:`.reset_agents`): ours, RCE on a classifier ensemble with
    priors; LNT / LNT-sparse, DDPG on a Q ensemble."""
    cfg, parts, kind = spec.cfg, speed_components(spec), spec.kind
    act_dim, head = action_spec.shape[-1], spec["reset.actor.head"]
    actor = make_actor(obs_dim, action_spec, cfg.hidden_sizes, parts, head)
    model, loss, groups = kind.build(spec, actor, obs_dim, act_dim, parts)
    terms = make_actor_terms(spec, actor, act_dim)
    if terms is not None and terms.entropy is not None:
        loss.entropy_bonus = terms.entropy  # saved and loaded with the loss's state
        if terms.entropy.learned:  # the temperature steps with the actor, at the classifiers' rate
            groups = [*groups, {"params": [terms.entropy.log_alpha], "lr": cfg.reset.critic_lr}]
    optimizer = make_adam(spec, groups)
    targets = parts.soft_update(loss, tau=reset_tau(spec))  # building it copies the networks into their targets
    # the targets that start as draws of their own (target_init: release for ours; algo.target_draws for LNT)
    for network, name in kind.fresh_targets(spec, loss, obs_dim, act_dim, parts,
                                            lambda: make_actor(obs_dim, action_spec, cfg.hidden_sizes, parts, head)):
        draw_target(getattr(loss, name), network)
    return Agent(actor, loss, optimizer, targets, model, kind.critic_loss, terms, head)


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
