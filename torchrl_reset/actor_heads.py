"""The reset actor's output heads, and what keeps a bounded actor's output from sticking at the edge of its box.

One object per kind of head builds the actor for a given action spec and sizes, says whether it explores by
its own samples or needs a noise module, gives its loss terms and measures its saturation:

- :class:`TanhHead`: the paper's deterministic actor, ``tanh`` onto the box, explored by added noise;
- :class:`InvertingHead`: a linear output clipped to the box with inverted gradients at the bounds;
- :class:`TanhNormalHead`: RCE's stochastic tanh-Gaussian actor (Eysenbach et al. 2021), exploring by its own
  samples, with an entropy temperature (fixed, or learned as SAC's): the project's reset actor.

:func:`actor_head` builds one by name (``"tanh"``, ``"inverting"``, ``"tanh_normal"``).

A DDPG-style actor ends in ``tanh``: once its pre-activation ``u`` lies deep in the tanh's flat tail, the
gradient that would bring it back is multiplied by ``1 - tanh(u)^2`` and never arrives. These are the
remedies a reset actor (or any bounded actor) can take, each usable on its own:

- :class:`InvertingGradientHead` (Hausknecht & Stone, ICLR 2016): no tanh; the actor's output is the
  action in the box's normalised coordinates, clipped for acting, and the action gradient is scaled by the
  distance to the bound it pushes towards (and reversed beyond it), so the output never leaves the box for
  long and a push back inside is never damped;
- :func:`actor_penalties`: ``c_u mean(u^2)`` on the pre-activation and ``c_a mean(a_n^2)`` on the normalised
  action (OpenAI HER's ``action_l2``);
- :class:`Temperature`: for a stochastic tanh-Gaussian actor, ``alpha * mean(log pi(a|s))`` with ``alpha``
  fixed or learned against a target entropy (SAC's temperature); :class:`~torchrl_reset.RCELoss` owns one
  when its actor is stochastic.

:func:`saturation` measures the trap: the share of action components beyond 0.99 of the bound and the mean
``|u|``.
"""
from __future__ import annotations

import math
from typing import Callable, ClassVar, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import (NormalParamExtractor, ProbabilisticTensorDictModule, TensorDictModule, TensorDictModuleBase,
                           TensorDictSequential)
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, TanhModule, TanhNormal

__all__ = ["ActorHead", "TanhHead", "InvertingHead", "TanhNormalHead", "ACTOR_HEADS", "actor_head", "head_from_settings", "is_stochastic",
           "paper_mlp", "InvertingGradients", "InvertingGradientHead", "actor_penalties", "Temperature", "saturation",
           "SATURATION_LEVEL"]

#: a component counts as saturated beyond this share of the way from the box's centre to its bound
SATURATION_LEVEL = 0.99


class InvertingGradients(torch.autograd.Function):
    """``clamp(u, -1, 1)`` forward; backward, the incoming gradient ``g = dL/da`` of a loss being minimised is
    scaled by ``(1 - u) / 2`` where it pushes ``a`` up (``g < 0``) and by ``(u + 1) / 2`` where it pushes
    down, with ``u`` unclipped: beyond a bound the factor turns negative and the step goes back inside."""

    @staticmethod
    def forward(ctx, u: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(u)
        return u.clamp(-1.0, 1.0)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        (u,) = ctx.saved_tensors
        return grad * torch.where(grad < 0, (1.0 - u) / 2.0, (u + 1.0) / 2.0)


class InvertingGradientHead(TensorDictModuleBase):
    """Maps the actor's output ``u`` (normalised coordinates, where the box is ``[-1, 1]``) onto the action box
    ``[low, high]``: ``action = mid + half * clamp(u, -1, 1)``, with :class:`InvertingGradients` backward.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> head = InvertingGradientHead(low=torch.tensor([0.0]), high=torch.tensor([2.0]))
        >>> td = head(TensorDict(action_preactivation=torch.tensor([[0.5], [3.0]]), batch_size=[2]))
        >>> td["action"].squeeze(-1).tolist()
        [1.5, 2.0]
    """

    def __init__(self, low: torch.Tensor, high: torch.Tensor, in_key: str = "action_preactivation",
                 out_key: str = "action") -> None:
        super().__init__()
        low, high = torch.as_tensor(low, dtype=torch.float32), torch.as_tensor(high, dtype=torch.float32)
        if not bool((high > low).all()):
            raise ValueError(f"every high bound must exceed its low bound, got low={low.tolist()}, high={high.tolist()}.")
        self.register_buffer("centre", (high + low) / 2)
        self.register_buffer("half_width", (high - low) / 2)
        self.in_keys, self.out_keys = [in_key], [out_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        u = tensordict.get(self.in_keys[0])
        return tensordict.set(self.out_keys[0], self.centre + self.half_width * InvertingGradients.apply(u))


def actor_penalties(preactivation: torch.Tensor, normalised_action: torch.Tensor, *, preact_penalty: float = 0.0,
                    action_l2: float = 0.0) -> torch.Tensor:
    """``preact_penalty * mean(u^2) + action_l2 * mean(a_n^2)`` over every entry (``a_n``: the action in the box's
    normalised coordinates, ``[-1, 1]``). Added to an actor's loss, it pulls ``u`` back towards 0."""
    total = preactivation.new_zeros(())
    if preact_penalty:
        total = total + preact_penalty * preactivation.pow(2).mean()
    if action_l2:
        total = total + action_l2 * normalised_action.pow(2).mean()
    return total


class Temperature(nn.Module):
    """The entropy temperature of a stochastic actor, with torchrl's ``SACLoss`` conventions.

    The actor's loss takes ``alpha * mean(log pi(a|s))`` (:meth:`actor_term`, alpha held fixed there); with a
    learned temperature (``fixed_alpha=False``), ``log alpha`` descends :meth:`loss`,
    ``-mean(log alpha * (log pi + target_entropy))`` (``log pi`` detached), which raises alpha while the
    policy's entropy is below the target and lowers it above (SAC's ``loss_alpha``).

    Args:
        alpha_init (float): alpha's first value (or its fixed value). Defaults to 0.01.

    Keyword Args:
        fixed_alpha (bool): keep alpha at ``alpha_init`` (a buffer, not a parameter). Defaults to False.
        target_entropy (float or "auto"): the entropy the learned alpha aims for; ``"auto"`` is
            ``-action_dim`` (SAC's). Defaults to ``"auto"``.
        action_dim (int, optional): the action's size, needed for ``target_entropy="auto"`` with a learned alpha.
        min_alpha, max_alpha (float, optional): bounds on alpha (``log alpha`` is clamped before it is used).

    Examples:
        >>> import math, torch
        >>> fixed = Temperature(0.5, fixed_alpha=True)
        >>> log_prob = torch.tensor([-1.0, -3.0])
        >>> float(fixed.actor_term(log_prob)), float(fixed.loss(log_prob))  # 0.5 * mean(log pi); nothing to learn
        (-1.0, 0.0)
        >>> learned = Temperature(0.5, action_dim=2)  # target entropy -2
        >>> round(float(learned.loss(log_prob)), 4) == round(-math.log(0.5) * (-2.0 - 2.0), 4)
        True
    """

    def __init__(self, alpha_init: float = 0.01, *, fixed_alpha: bool = False, target_entropy: float | str = "auto",
                 action_dim: int | None = None, min_alpha: float | None = None,
                 max_alpha: float | None = None) -> None:
        super().__init__()
        if not alpha_init > 0:
            raise ValueError(f"alpha_init must be positive, got {alpha_init!r}.")
        for name, bound in (("min_alpha", min_alpha), ("max_alpha", max_alpha)):
            if bound is not None and not bound > 0:
                raise ValueError(f"{name} must be positive (or None), got {bound!r}.")
        if min_alpha is not None and max_alpha is not None and not min_alpha <= max_alpha:
            raise ValueError(f"min_alpha ({min_alpha}) must not exceed max_alpha ({max_alpha}).")
        self.fixed_alpha = bool(fixed_alpha)
        if self.fixed_alpha:
            self.target_entropy = None
        elif target_entropy == "auto":
            if action_dim is None or int(action_dim) < 1:
                raise ValueError("target_entropy='auto' is -dim(A): pass action_dim (a positive int), "
                                 f"got {action_dim!r}.")
            self.target_entropy = -float(action_dim)
        elif isinstance(target_entropy, str):
            raise ValueError(f"target_entropy must be a number or 'auto', got {target_entropy!r}.")
        else:
            self.target_entropy = float(target_entropy)
        self.min_log_alpha = None if min_alpha is None else math.log(min_alpha)
        self.max_log_alpha = None if max_alpha is None else math.log(max_alpha)
        log_alpha = torch.tensor(math.log(alpha_init))
        if self.learned:
            self.log_alpha = nn.Parameter(log_alpha)
        else:
            self.register_buffer("log_alpha", log_alpha)

    @property
    def learned(self) -> bool:
        return not self.fixed_alpha

    def _log_alpha(self) -> torch.Tensor:
        if self.min_log_alpha is not None or self.max_log_alpha is not None:
            with torch.no_grad():  # as SACLoss: the parameter itself is kept inside the bounds
                self.log_alpha.clamp_(self.min_log_alpha, self.max_log_alpha)
        return self.log_alpha

    @property
    def alpha(self) -> torch.Tensor:
        """alpha now (no gradient)."""
        return self._log_alpha().detach().exp()

    def actor_term(self, log_prob: torch.Tensor) -> torch.Tensor:
        """``alpha * mean(log pi)``, the actor's entropy term: its gradient reaches the actor only."""
        return self.alpha * log_prob.mean()

    def loss(self, log_prob: torch.Tensor) -> torch.Tensor:
        """The temperature's loss, ``-mean(log alpha * (log pi + target))`` (gradient to ``log alpha`` only); 0
        for a fixed alpha."""
        if not self.learned:
            return log_prob.new_zeros(())
        return -(self._log_alpha() * (log_prob.detach() + self.target_entropy)).mean()

    def extra_repr(self) -> str:
        return f"alpha={float(self.alpha):.4g}, learned={self.learned}, target_entropy={self.target_entropy}"


def saturation(normalised_action: torch.Tensor, preactivation: torch.Tensor) -> tuple[int, int, float]:
    """``(saturated, components, sum |u|)``: how many action components (normalised coordinates) lie beyond
    :data:`SATURATION_LEVEL` of the bound, out of how many, and the sum of ``|u|`` over them."""
    return (int((normalised_action.abs() > SATURATION_LEVEL).sum()), normalised_action.numel(),
            float(preactivation.abs().sum()))


def paper_mlp(in_features: int, out_features: int, hidden_sizes: Sequence[int] = (400, 300)) -> nn.Sequential:
    """The paper's policy network: ReLU layers of ``hidden_sizes``, Xavier-uniform weights and zero biases."""
    layers, width = [], in_features
    for size in hidden_sizes:
        layers += [nn.Linear(width, size), nn.ReLU()]
        width = size
    layers.append(nn.Linear(width, out_features))
    net = nn.Sequential(*layers)
    for layer in net:
        if isinstance(layer, nn.Linear):
            nn.init.xavier_uniform_(layer.weight)
            nn.init.zeros_(layer.bias)
    return net


def is_stochastic(actor: nn.Module) -> bool:
    """Whether ``actor`` draws its action from a distribution (it holds a probabilistic tensordict module)."""
    return any(isinstance(module, ProbabilisticTensorDictModule) for module in actor.modules())


def _plain_module(module: nn.Module, in_key: str, out_key: str) -> TensorDictModule:
    return TensorDictModule(module, in_keys=[in_key], out_keys=[out_key])


class ActorHead:
    """How an actor's network output becomes an action in the box, and what that implies.

    A head builds the actor (:meth:`make_actor`: the paper's MLP, or :meth:`build` around a network of your
    own), says whether it explores by its own samples (:attr:`stochastic`: no noise module needed) or needs
    one, gives its loss terms (:meth:`loss_kwargs` for :class:`~torchrl_reset.RCELoss`, :meth:`penalty` for
    the penalties on its pre-activation and action) and measures its saturation (:meth:`saturation`). Every
    head writes the pre-activation ``action_preactivation`` beside ``action``.

    Keyword Args:
        preact_penalty (float): ``c`` of ``c * mean(u^2)`` on the pre-activation ``u``. Defaults to 0.
        action_l2 (float): ``c`` of ``c * mean(a^2)`` on the action in normalised coordinates. Defaults to 0.
    """

    name: ClassVar[str]
    #: whether the actor explores by sampling its own distribution (True) or needs added noise (False)
    stochastic: ClassVar[bool] = False
    preactivation_key: ClassVar[str] = "action_preactivation"

    def __init__(self, *, preact_penalty: float = 0.0, action_l2: float = 0.0) -> None:
        for key, value in (("preact_penalty", preact_penalty), ("action_l2", action_l2)):
            if not float(value) >= 0:
                raise ValueError(f"{key} must be a number >= 0, got {value!r}.")
        self.preact_penalty, self.action_l2 = float(preact_penalty), float(action_l2)

    @classmethod
    def from_settings(cls, *, preact_penalty: float = 0.0, action_l2: float = 0.0, **others) -> "ActorHead":
        """The head from a configuration's settings (the recipe's ``reset.actor.*``); settings of other heads
        (a tanh-Gaussian's ``entropy``) are ignored."""
        return cls(preact_penalty=preact_penalty, action_l2=action_l2)

    def out_features(self, action_dim: int) -> int:
        """The network's output size for an action of ``action_dim`` components."""
        return action_dim

    def make_actor(self, obs_dim: int, action_spec, hidden_sizes: Sequence[int] = (400, 300), *,
                   in_key: str = "observation",
                   tensor_module: Callable[[nn.Module, str, str], TensorDictModuleBase] | None = None
                   ) -> TensorDictSequential:
        """The paper's actor network (:func:`paper_mlp`) with this head, reading ``in_key``. ``tensor_module``
        wraps the network as a tensordict module (``torchrl_reset.accel.Components.tensor_module`` for the
        fast path; default ``TensorDictModule``)."""
        net = paper_mlp(obs_dim, self.out_features(action_spec.shape[-1]), hidden_sizes)
        return self.build(net, action_spec, in_key=in_key, tensor_module=tensor_module)

    def build(self, network: nn.Module, action_spec, *, in_key: str = "observation",
              tensor_module: Callable[[nn.Module, str, str], TensorDictModuleBase] | None = None
              ) -> TensorDictSequential:
        """The actor: ``network`` (``in_key`` to :meth:`out_features` outputs) followed by this head."""
        raise NotImplementedError

    def normalised_action(self, preactivation: torch.Tensor) -> torch.Tensor:
        """The noiseless action in the box's normalised coordinates (``[-1, 1]``) from the pre-activation."""
        return torch.tanh(preactivation)

    def saturation(self, preactivation: torch.Tensor) -> tuple[int, int, float]:
        """:func:`saturation` of the noiseless action: ``(saturated, components, sum |u|)``."""
        return saturation(self.normalised_action(preactivation), preactivation)

    def loss_kwargs(self) -> dict:
        """What this head asks of :class:`~torchrl_reset.RCELoss` (the temperature's arguments for a stochastic
        head; nothing for a deterministic one)."""
        return {}

    @property
    def has_penalty(self) -> bool:
        return bool(self.preact_penalty or self.action_l2)

    def penalty(self, actor: TensorDictModuleBase, tensordict: TensorDictBase) -> torch.Tensor | None:
        """The penalties on ``actor``'s pre-activation and action at the states of ``tensordict``
        (:func:`actor_penalties`; the actor's noiseless pass), to add to its loss; None where both are 0."""
        if not self.has_penalty:
            return None
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            u = actor(tensordict.select(*actor.in_keys)).get(self.preactivation_key)
        return actor_penalties(u, self.normalised_action(u), preact_penalty=self.preact_penalty,
                               action_l2=self.action_l2)

    def __repr__(self) -> str:
        extra = "".join(f", {k}={getattr(self, k)}" for k in ("preact_penalty", "action_l2") if getattr(self, k))
        return f"{type(self).__name__}(name={self.name!r}, stochastic={self.stochastic}{extra})"


class TanhHead(ActorHead):
    """The paper's deterministic actor: ``tanh`` of the network's output onto the box (torchrl's ``TanhModule``),
    explored by added noise (the release's Ornstein-Uhlenbeck process).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> _ = torch.manual_seed(0)
        >>> head = TanhHead()
        >>> actor = head.make_actor(3, Bounded(-2.0, 2.0, shape=(2,)), hidden_sizes=(8,))
        >>> td = actor(TensorDict(observation=torch.randn(4, 3), batch_size=[4]))
        >>> bool(torch.allclose(td["action"], 2.0 * torch.tanh(td["action_preactivation"])))
        True
        >>> head.stochastic
        False
    """

    name = "tanh"

    def build(self, network, action_spec, *, in_key="observation", tensor_module=None):
        wrap = tensor_module or _plain_module
        return TensorDictSequential(wrap(network, in_key, self.preactivation_key),
                                    TanhModule([self.preactivation_key], ["action"], spec=action_spec))


class InvertingHead(ActorHead):
    """A linear output clipped to the box, its action gradient inverted at the bounds
    (:class:`InvertingGradientHead`, Hausknecht & Stone 2016); explored by added noise."""

    name = "inverting"

    def build(self, network, action_spec, *, in_key="observation", tensor_module=None):
        wrap = tensor_module or _plain_module
        return TensorDictSequential(wrap(network, in_key, self.preactivation_key),
                                    InvertingGradientHead(action_spec.space.low, action_spec.space.high))

    def normalised_action(self, preactivation):
        return preactivation.clamp(-1.0, 1.0)


class TanhNormalHead(ActorHead):
    """RCE's stochastic actor: a torchrl ``ProbabilisticActor`` on a ``TanhNormal`` onto the box, whose location is
    the pre-activation. It samples (reparameterised) in ``ExplorationType.RANDOM``, the collector's mode, and
    acts ``tanh(loc)`` onto the box otherwise; it writes ``action_log_prob``. It explores by its own samples (no
    noise module) and its loss takes an entropy temperature (:class:`Temperature`).

    Keyword Args:
        alpha_init (float): the temperature's first value (or its fixed value). Defaults to 0.01 (the
            project's; RCE's fixed coefficient is 1e-4, SAC starts at 1 for rewards in the hundreds, where
            this actor's objective, a probability, stays below 1).
        fixed_alpha (bool): keep alpha at ``alpha_init``. Defaults to False (learned towards ``target_entropy``).
        target_entropy (float or "auto"): defaults to ``"auto"``, ``-dim(A)`` as SAC.
        preact_penalty, action_l2: as :class:`ActorHead`.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> from torchrl.envs.utils import ExplorationType, set_exploration_type
        >>> _ = torch.manual_seed(0)
        >>> head = TanhNormalHead()
        >>> actor = head.make_actor(3, Bounded(0.0, 2.0, shape=(2,)), hidden_sizes=(8,))
        >>> td = TensorDict(observation=torch.randn(4, 3), batch_size=[4])
        >>> mean = actor(td.clone())  # noiseless: tanh(loc) onto [0, 2]
        >>> bool(torch.allclose(mean["action"], 1.0 + torch.tanh(mean["action_preactivation"]), atol=1e-6))
        True
        >>> with set_exploration_type(ExplorationType.RANDOM):
        ...     drawn = actor(td.clone())
        >>> sorted(k for k in drawn.keys() if k.startswith("action"))
        ['action', 'action_log_prob', 'action_preactivation', 'action_scale']
        >>> head.stochastic, head.loss_kwargs()
        (True, {'alpha_init': 0.01, 'fixed_alpha': False, 'target_entropy': 'auto'})
    """

    name = "tanh_normal"
    stochastic = True

    def __init__(self, *, alpha_init: float = 0.01, fixed_alpha: bool = False, target_entropy: float | str = "auto",
                 preact_penalty: float = 0.0, action_l2: float = 0.0) -> None:
        super().__init__(preact_penalty=preact_penalty, action_l2=action_l2)
        if not float(alpha_init) > 0:
            raise ValueError(f"alpha_init must be positive, got {alpha_init!r}.")
        self.alpha_init, self.fixed_alpha, self.target_entropy = float(alpha_init), bool(fixed_alpha), target_entropy

    @classmethod
    def from_settings(cls, *, entropy: float | str = "auto", preact_penalty: float = 0.0, action_l2: float = 0.0,
                      **others) -> "TanhNormalHead":
        """``entropy``: ``"auto"``, the temperature learned from 0.01 towards ``-dim(A)``; a number, alpha fixed
        there (RCE's original: 1e-4)."""
        if entropy == "auto":
            return cls(preact_penalty=preact_penalty, action_l2=action_l2)
        return cls(alpha_init=float(entropy), fixed_alpha=True, preact_penalty=preact_penalty, action_l2=action_l2)

    def out_features(self, action_dim: int) -> int:
        return 2 * action_dim  # the Gaussian's location and scale

    def build(self, network, action_spec, *, in_key="observation", tensor_module=None):
        module = TensorDictModule(nn.Sequential(network, NormalParamExtractor()), in_keys=[in_key],
                                  out_keys=[self.preactivation_key, "action_scale"])
        low, high = action_spec.space.low, action_spec.space.high
        return TensorDictSequential(ProbabilisticActor(
            module, in_keys={"loc": self.preactivation_key, "scale": "action_scale"}, spec=action_spec,
            distribution_class=TanhNormal, distribution_kwargs={"low": low, "high": high}, return_log_prob=True))

    def loss_kwargs(self) -> dict:
        return {"alpha_init": self.alpha_init, "fixed_alpha": self.fixed_alpha, "target_entropy": self.target_entropy}


#: the heads by name
ACTOR_HEADS: dict[str, type[ActorHead]] = {head.name: head for head in (TanhHead, InvertingHead, TanhNormalHead)}


def actor_head(name: str, **kwargs) -> ActorHead:
    """The head called ``name`` (:data:`ACTOR_HEADS`), built with ``kwargs`` (its constructor's arguments).

    Examples:
        >>> actor_head("tanh_normal", fixed_alpha=True, alpha_init=1e-4)
        TanhNormalHead(name='tanh_normal', stochastic=True)
    """
    if name not in ACTOR_HEADS:
        raise ValueError(f"unknown actor head {name!r}; known: {', '.join(ACTOR_HEADS)}.")
    return ACTOR_HEADS[name](**kwargs)


def head_from_settings(name: str, **settings) -> ActorHead:
    """The head called ``name`` from a configuration's settings (:meth:`ActorHead.from_settings`).

    Examples:
        >>> head_from_settings("tanh_normal", entropy=1e-4).loss_kwargs()
        {'alpha_init': 0.0001, 'fixed_alpha': True, 'target_entropy': 'auto'}
        >>> head_from_settings("tanh", preact_penalty=0.01, entropy="auto")
        TanhHead(name='tanh', stochastic=False, preact_penalty=0.01)
    """
    if name not in ACTOR_HEADS:
        raise ValueError(f"unknown actor head {name!r}; known: {', '.join(ACTOR_HEADS)}.")
    return ACTOR_HEADS[name].from_settings(**settings)
