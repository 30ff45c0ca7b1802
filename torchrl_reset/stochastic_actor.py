"""SAC's conventions for a loss whose actor may be stochastic: the entropy temperature, ``loss_alpha``, ``alpha``
and ``entropy``, shared by :class:`~torchrl_reset.RCELoss` and the DDPG losses of the LNT reset agents."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import DDPGLoss

from .actor_heads import Temperature, is_stochastic

__all__ = ["StochasticActorMixin", "EntropyDDPGLoss", "ENTROPY_SAMPLES"]

#: where the actor's ``log pi`` comes from: ``own``, a second reparameterised sample at the same states (an
#: unbiased estimate of ``E[log pi]`` of its own beside the sample the value term scores); ``shared``, the
#: log-probability of the very action the value term scores (SACLoss's)
ENTROPY_SAMPLES = ("own", "shared")


def _action_dim(actor: TensorDictModuleBase, action_spec) -> int | None:
    spec = action_spec
    if spec is None:  # a ProbabilisticActor keeps the action spec it was built with
        spec = next((m.spec for m in actor.modules() if getattr(m, "spec", None) is not None), None)
        spec = spec.get("action", spec) if hasattr(spec, "keys") and "action" in spec.keys() else spec
    return None if spec is None else int(spec.shape[-1])


def _rename_entropy_bonus(state_dict, prefix, *args) -> None:
    """State dicts written before the temperature was the loss's own keep it as ``entropy_bonus.log_alpha``."""
    old, new = f"{prefix}entropy_bonus.log_alpha", f"{prefix}temperature.log_alpha"
    if old in state_dict and new not in state_dict:
        state_dict[new] = state_dict.pop(old)


class StochasticActorMixin:
    """Gives a loss module SAC's temperature when its actor is stochastic (``is_stochastic``): the actor's loss
    then samples reparameterised actions (``ExplorationType.RANDOM``) and adds ``alpha * mean(log pi(a|s))``;
    :meth:`loss_alpha` is the temperature's loss, and the temperature's parameter is the loss's own
    (``loss.parameters()`` gives an optimizer everything). A deterministic actor changes nothing."""

    log_prob_key = "action_log_prob"

    def _init_temperature(self, actor_network: TensorDictModuleBase, *, alpha_init: float, fixed_alpha: bool,
                          target_entropy, min_alpha: float | None, max_alpha: float | None, action_spec,
                          entropy_sample: str) -> None:
        if entropy_sample not in ENTROPY_SAMPLES:
            raise ValueError(f"entropy_sample must be one of {ENTROPY_SAMPLES}, got {entropy_sample!r}.")
        self.stochastic = is_stochastic(actor_network)
        self.entropy_sample = entropy_sample
        self._register_load_state_dict_pre_hook(_rename_entropy_bonus)
        if not self.stochastic:
            self.temperature = None
            return
        action_dim = _action_dim(actor_network, action_spec)
        if action_dim is None and not fixed_alpha and target_entropy == "auto":
            raise ValueError("target_entropy='auto' is -dim(A): pass action_spec=..., or an actor that keeps its spec "
                             "(torchrl's ProbabilisticActor(spec=...)), or a number.")
        self.temperature = Temperature(alpha_init, fixed_alpha=fixed_alpha, target_entropy=target_entropy,
                                       action_dim=action_dim, min_alpha=min_alpha, max_alpha=max_alpha)

    @property
    def alpha(self) -> torch.Tensor | None:
        """The temperature now, or None for a deterministic actor."""
        return None if self.temperature is None else self.temperature.alpha

    def loss_alpha(self, log_prob: torch.Tensor) -> torch.Tensor:
        """The temperature's loss from the actor's ``log pi`` (:meth:`loss_actor`'s metadata ``log_prob``); 0 for
        a fixed temperature. SACLoss's ``loss_alpha``."""
        if self.temperature is None:
            raise RuntimeError("loss_alpha needs a stochastic actor; this loss's actor is deterministic.")
        return self.temperature.loss(log_prob)

    def _entropy_terms(self, value_loss, acted: TensorDictBase, act_again) -> tuple[torch.Tensor, dict]:
        """``value_loss + alpha * mean(log pi)`` and the metadata (``log_prob`` detached, ``entropy``, ``alpha``).
        ``acted``: the actor's output whose action ``value_loss`` scored; ``act_again()``: a second pass."""
        source = acted if self.entropy_sample == "shared" else act_again()
        log_prob = source.get(self.log_prob_key)
        loss = value_loss + self.temperature.actor_term(log_prob)
        detached = log_prob.detach()
        return loss, {"log_prob": detached, "entropy": -detached.mean(), "alpha": self.temperature.alpha}


class EntropyDDPGLoss(StochasticActorMixin, DDPGLoss):
    """torchrl's ``DDPGLoss`` whose actor may be stochastic (LNT's reset agent with the project's actor): with a
    ``ProbabilisticActor``, :meth:`loss_actor` scores a reparameterised sample with the critic and adds
    ``alpha * mean(log pi)`` from a sample of its own (``entropy_sample="own"``, the only choice here: the
    critic's pass is torchrl's); the temperature is :class:`~torchrl_reset.actor_heads.Temperature`. With a
    deterministic actor it is ``DDPGLoss`` exactly. The TD targets take the target actor's deterministic
    action.

    Keyword Args:
        alpha_init, fixed_alpha, target_entropy, min_alpha, max_alpha, action_spec: the temperature's, as
            :class:`~torchrl_reset.RCELoss`.
        Everything else: ``DDPGLoss``'s.
    """

    def __init__(self, actor_network, value_network, *, alpha_init: float = 0.01, fixed_alpha: bool = False,
                 target_entropy="auto", min_alpha: float | None = None, max_alpha: float | None = None,
                 action_spec=None, **kwargs) -> None:
        super().__init__(actor_network, value_network, **kwargs)
        self._init_temperature(actor_network, alpha_init=alpha_init, fixed_alpha=fixed_alpha,
                               target_entropy=target_entropy, min_alpha=min_alpha, max_alpha=max_alpha,
                               action_spec=action_spec, entropy_sample="own")

    def loss_actor(self, tensordict: TensorDictBase):
        if not self.stochastic:
            return super().loss_actor(tensordict)
        with set_exploration_type(ExplorationType.RANDOM):
            value_loss, metadata = super().loss_actor(tensordict)

            def act_again():
                with self.actor_network_params.to_module(self.actor_network):
                    return self.actor_network(tensordict.select(*self.actor_network.in_keys))

            loss, entropy = self._entropy_terms(value_loss, None, act_again)
        return loss, {**metadata, **entropy}

    def forward(self, tensordict: TensorDictBase):
        """``DDPGLoss``'s output; with a stochastic actor also ``loss_alpha``, ``alpha`` and ``entropy``."""
        out = super().forward(tensordict)
        if self.stochastic:
            out.set("loss_alpha", self.loss_alpha(out.pop("log_prob")))
        return out
