"""The reset agent's critic: an ensemble of success classifiers with randomized prior functions.

Paper: Kim et al., "Automating Reinforcement Learning with Example-based Resets" (RA-L 2022),
"Reset trigger mechanism" and "Hyperparameters"; randomized priors from Osband et al. (2018).
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn

from ._validation import check_int, is_int_at_least

__all__ = [
    "EnsembleValueOperator",
    "PRIOR_BIAS_DRAWS",
    "prior_bias_bound",
    "with_prior",
    "reduce_members",
    "success_classifier",
    "success_probability",
]

MEMBER_REDUCTIONS = ("mean", "min", "max")
PRIOR_BIAS_DRAWS = ("xavier", "fan_in")


def prior_bias_bound(draw: str, fan_in: int, fan_out: int) -> float:
    """The half-width of the uniform draw of a prior layer's bias (``fan_out`` units, ``fan_in`` inputs).

    ``"xavier"`` (the authors' release, docs/method.md section 9): the same Xavier-uniform initializer
    as the weights, which reads a bias of shape ``[n]`` as fan_in = fan_out = n, so
    ``sqrt(6 / (n + n)) = sqrt(3 / fan_out)``: 1.73 for a one-unit output layer, about 0.087 for 400
    units. ``"fan_in"``: ``1 / sqrt(fan_in)``, the bound of ``torch.nn.Linear``'s bias (this project's
    draw before it followed the release; 0.058 on a 300-unit input).
    """
    if draw == "xavier":
        return math.sqrt(3.0 / fan_out)
    if draw == "fan_in":
        return 1.0 / math.sqrt(fan_in)
    raise ValueError(f"prior_bias_draw must be one of {PRIOR_BIAS_DRAWS}, got {draw!r}.")


def success_classifier(logits: torch.Tensor) -> torch.Tensor:
    """The classifier value ``C = sigmoid(logit)``, in [0, 1]."""
    return torch.sigmoid(logits)


def success_probability(logits: torch.Tensor) -> torch.Tensor:
    """The classifier ratio ``p = C / (1 - C)`` with ``C`` clipped to [0, 0.5] first.

    ``sigmoid(l) / (1 - sigmoid(l)) = exp(l)`` and ``C <= 0.5`` is ``l <= 0``, so the clipped ratio is
    ``exp(min(l, 0))``: the same number, computed without cancellation. The result lies in [0, 1].
    """
    return torch.exp(logits.clamp(max=0.0))


def with_prior(trained: torch.Tensor, prior: torch.Tensor, prior_scale: float) -> torch.Tensor:
    """Randomized prior functions (Osband et al., 2018): member i's logit ``f_i(s, a) + beta * g_i(s, a)``,
    from the trained part's output ``f`` and the fixed prior's ``g`` (any shapes that broadcast)."""
    return trained + prior_scale * prior


def reduce_members(values: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """Reduces the trailing ensemble-member dimension with ``"mean"``, ``"min"`` or ``"max"``."""
    if reduction == "mean":
        return values.mean(-1)
    if reduction == "min":
        return values.amin(-1)
    if reduction == "max":
        return values.amax(-1)
    raise ValueError(f"reduction must be one of {MEMBER_REDUCTIONS}, got {reduction!r}.")


def _xavier_uniform_(weight: torch.Tensor, fan_in: int, fan_out: int) -> None:
    bound = math.sqrt(6.0 / (fan_in + fan_out))
    with torch.no_grad():
        weight.uniform_(-bound, bound)


class EnsembleValueOperator(TensorDictModuleBase):
    """K state-action classifiers evaluated together, each with its own randomized prior function.

    Every member has the paper's critic architecture: the observation enters the first layer, the
    action is joined to the first hidden layer's output, ReLU hidden layers (400, 300 by default)
    and one output logit. Member ``i`` returns ``logit_i(s, a) = f_i(s, a) + beta * g_i(s, a)``,
    where ``g_i`` has the same architecture, its own random initialisation (biases included) and
    is never trained: its weights are buffers, so they are in no optimizer, and a target copy made
    by :class:`~torchrl.objectives.SoftUpdate` keeps them unchanged. All members are evaluated by
    batched matrix products (no Python loop over members). This class is the plain reference;
    :class:`torchrl_reset.accel.FastEnsembleValueOperator` computes the same numbers faster.

    Trainable weights use Xavier-uniform initialisation and zero biases (docs/method.md section 5);
    the priors' weights are Xavier-uniform too and their biases are drawn by ``prior_bias_draw``.

    Args:
        observation_dim (int): size of the observation (the sum of the sizes of all observation
            keys when several are given).
        action_dim (int): size of the action.

    Keyword Args:
        num_members (int): the ensemble size K. Defaults to 5.
        hidden_sizes (sequence of int): hidden layer sizes. Defaults to ``(400, 300)``.
        prior_scale (float): the prior scale beta. ``0`` disables the priors. Defaults to 3.
        prior_bias_draw (str): how the priors' biases are drawn (:func:`prior_bias_bound`):
            ``"xavier"``, the release's ``U(+-sqrt(3 / n))`` for a layer of ``n`` units (the output
            layer's bias, up to +-1.73, gives each member a constant logit offset of up to
            +-beta 1.73), or ``"fan_in"``, ``U(+-1 / sqrt(fan_in))``. Defaults to ``"xavier"``.
        in_keys (sequence of NestedKey): observation key(s) followed by the action key, last.
            Defaults to ``("observation", "action")``.
        out_keys (sequence of NestedKey): one key for the per-member logits, shaped
            ``[*batch, K]``. Defaults to ``("state_action_logit",)``.
        device, dtype: where and how the parameters are created.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_reset import EnsembleValueOperator, success_probability
        >>> torch.manual_seed(0)  # doctest: +ELLIPSIS
        <...>
        >>> ensemble = EnsembleValueOperator(3, 2, num_members=4, hidden_sizes=(16, 16))
        >>> td = TensorDict(observation=torch.randn(10, 3), action=torch.rand(10, 2), batch_size=[10])
        >>> td = ensemble(td)
        >>> td["state_action_logit"].shape
        torch.Size([10, 4])
        >>> p = success_probability(td["state_action_logit"])  # in [0, 1]
        >>> bool(((p >= 0) & (p <= 1)).all())
        True
        >>> sum(p.numel() for p in ensemble.parameters())  # priors are buffers, not parameters
        1540
    """

    def __init__(
        self,
        observation_dim: int,
        action_dim: int,
        *,
        num_members: int = 5,
        hidden_sizes: Sequence[int] = (400, 300),
        prior_scale: float = 3.0,
        prior_bias_draw: str = "xavier",
        in_keys: Sequence[NestedKey] = ("observation", "action"),
        out_keys: Sequence[NestedKey] = ("state_action_logit",),
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        check_int("observation_dim", observation_dim)
        check_int("action_dim", action_dim)
        check_int("num_members (the ensemble size K)", num_members)
        hidden_sizes = tuple(hidden_sizes)
        if not hidden_sizes or not all(is_int_at_least(h, 1) for h in hidden_sizes):
            raise ValueError(f"hidden_sizes must be a non-empty sequence of positive integers, got {hidden_sizes!r}.")
        prior_scale = float(prior_scale)
        if not math.isfinite(prior_scale) or prior_scale < 0:
            raise ValueError(f"prior_scale must be a finite number >= 0, got {prior_scale!r}.")
        prior_bias_bound(prior_bias_draw, 1, 1)  # refuses an unknown draw
        in_keys = list(in_keys)
        out_keys = list(out_keys)
        if len(in_keys) < 2:
            raise ValueError(f"in_keys must name at least one observation key and the action key (last), got {in_keys!r}.")
        if len(out_keys) != 1:
            raise ValueError(f"out_keys must hold exactly one key (the per-member logits), got {out_keys!r}.")
        self.in_keys = in_keys
        self.out_keys = out_keys
        self.observation_dim = observation_dim
        self.action_dim = action_dim
        self.num_members = num_members
        self.hidden_sizes = hidden_sizes
        self.prior_scale = prior_scale
        self.prior_bias_draw = prior_bias_draw

        factory = {"device": device, "dtype": dtype}
        sizes_in = (observation_dim, *hidden_sizes)
        sizes_out = (*hidden_sizes, 1)
        self.num_layers = len(sizes_in)
        k = num_members
        for i, (n_in, n_out) in enumerate(zip(sizes_in, sizes_out)):
            self.register_parameter(f"weight_{i}", nn.Parameter(torch.empty(k, n_in, n_out, **factory)))
            self.register_parameter(f"bias_{i}", nn.Parameter(torch.empty(k, n_out, **factory)))
        self.action_weight = nn.Parameter(torch.empty(k, action_dim, sizes_out[1], **factory))
        if prior_scale > 0:
            for i, (n_in, n_out) in enumerate(zip(sizes_in, sizes_out)):
                self.register_buffer(f"prior_weight_{i}", torch.empty(k, n_in, n_out, **factory))
                self.register_buffer(f"prior_bias_{i}", torch.empty(k, n_out, **factory))
            self.register_buffer("prior_action_weight", torch.empty(k, action_dim, sizes_out[1], **factory))
        self.reset_parameters()

    @property
    def has_prior(self) -> bool:
        return self.prior_scale > 0

    def reset_parameters(self) -> None:
        """Xavier-uniform weights and zero biases for the trained part; a fresh random prior (Xavier-uniform
        weights, biases drawn by ``prior_bias_draw``)."""
        sizes_in = (self.observation_dim, *self.hidden_sizes)
        sizes_out = (*self.hidden_sizes, 1)
        prefixes = ["", "prior_"] if self.has_prior else [""]
        for prefix in prefixes:
            for i, (n_in, n_out) in enumerate(zip(sizes_in, sizes_out)):
                # The action joins the input of layer 1: fan-in counts both parts.
                fan_in = n_in + (self.action_dim if i == 1 else 0)
                _xavier_uniform_(getattr(self, f"{prefix}weight_{i}"), fan_in, n_out)
                if i == 1:
                    _xavier_uniform_(getattr(self, f"{prefix}action_weight"), fan_in, n_out)
                bias = getattr(self, f"{prefix}bias_{i}")
                with torch.no_grad():
                    if prefix:
                        bound = prior_bias_bound(self.prior_bias_draw, fan_in, n_out)
                        bias.uniform_(-bound, bound)
                    else:
                        bias.zero_()

    def layer_tensors(
        self, params: TensorDictBase | None = None, prefix: str = ""
    ) -> tuple[list[torch.Tensor], list[torch.Tensor], torch.Tensor]:
        """The stacked weights, biases and action weight of the trained (``prefix=""``) or prior
        (``prefix="prior_"``) members, read from ``params`` (a tensordict of this module's parameters
        and buffers, such as a loss module's functional or target copy) or from the module itself."""
        get = (lambda name: getattr(self, name)) if params is None else params.get
        weights = [get(f"{prefix}weight_{i}") for i in range(self.num_layers)]
        biases = [get(f"{prefix}bias_{i}") for i in range(self.num_layers)]
        return weights, biases, get(f"{prefix}action_weight")

    @staticmethod
    def members_forward(
        obs: torch.Tensor,
        action: torch.Tensor,
        weights: list[torch.Tensor],
        biases: list[torch.Tensor],
        action_weight: torch.Tensor,
    ) -> torch.Tensor:
        """M stacked members on shared inputs ``obs`` [N, d] and ``action`` [N, a]; returns [M, N] outputs.

        The paper's critic layout, member by member along the leading dimension: the state enters
        the first layer, the action joins the first hidden layer's output.
        """
        hidden = torch.relu(obs @ weights[0] + biases[0].unsqueeze(-2))  # [N, d] @ [M, d, h0] -> [M, N, h0]
        hidden = hidden @ weights[1] + action @ action_weight + biases[1].unsqueeze(-2)
        for i in range(2, len(weights)):
            hidden = torch.relu(hidden) @ weights[i] + biases[i].unsqueeze(-2)
        return hidden.squeeze(-1)

    def _check_inputs(self, observation: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if observation.shape[-1:] != (self.observation_dim,):
            raise ValueError(
                f"EnsembleValueOperator expects observations of size {self.observation_dim} in the last "
                f"dimension, got shape {tuple(observation.shape)}."
            )
        if action.shape[-1:] != (self.action_dim,):
            raise ValueError(
                f"EnsembleValueOperator expects actions of size {self.action_dim} in the last dimension, "
                f"got shape {tuple(action.shape)}."
            )
        if action.shape[:-1] != observation.shape[:-1]:
            raise ValueError(
                f"observation and action batch shapes differ: {tuple(observation.shape[:-1])} vs {tuple(action.shape[:-1])}."
            )
        obs = observation.reshape(-1, self.observation_dim)
        return obs, action.reshape(-1, self.action_dim).to(obs.dtype)

    def logits(
        self, observation: torch.Tensor, action: torch.Tensor, params: TensorDictBase | None = None
    ) -> torch.Tensor:
        """Per-member logits ``f_i(s, a) + beta * g_i(s, a)`` for a batch of (observation, action) pairs.

        Args:
            observation (Tensor): ``[*batch, observation_dim]``.
            action (Tensor): ``[*batch, action_dim]``.
            params (TensorDictBase, optional): the parameters and buffers to use instead of the
                module's own (for instance a loss module's target copy).

        Returns:
            ``[*batch, K]`` logits.
        """
        batch = observation.shape[:-1]
        obs, act = self._check_inputs(observation, action)
        return self.members_logits(obs, act, params).transpose(0, 1).reshape(*batch, self.num_members)

    def members_logits(self, obs: torch.Tensor, action: torch.Tensor, params: TensorDictBase | None = None) -> torch.Tensor:
        """``[M, N]`` logits ``f_i(s, a) + beta * g_i(s, a)`` of the members on ``obs`` ``[N, d]`` and
        ``action`` ``[N, a]``, or on per-member inputs ``[M, N, d]`` and ``[M, N, a]`` (the plain
        products broadcast either)."""
        plain = EnsembleValueOperator.members_forward
        f = plain(obs, action, *self.layer_tensors(params))  # f_i(s, a), trained
        if not self.has_prior:
            return f
        g = plain(obs, action, *self.layer_tensors(params, "prior_"))  # g_i(s, a), fixed
        return with_prior(f, g, self.prior_scale)

    def observation_from(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The observation entries this module reads, joined along the last dimension."""
        observations = []
        for key in self.in_keys[:-1]:
            value = tensordict.get(key, None)
            if value is None:
                raise KeyError(
                    f"EnsembleValueOperator needs the observation key {key!r}; the tensordict has "
                    f"{sorted(map(str, tensordict.keys(True, True)))}."
                )
            observations.append(value)
        return observations[0] if len(observations) == 1 else torch.cat(observations, -1)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        observation = self.observation_from(tensordict)
        action = tensordict.get(self.in_keys[-1], None)
        if action is None:
            raise KeyError(
                f"EnsembleValueOperator needs the action key {self.in_keys[-1]!r}; the tensordict has "
                f"{sorted(map(str, tensordict.keys(True, True)))}."
            )
        tensordict.set(self.out_keys[0], self.logits(observation, action))
        return tensordict

    def extra_repr(self) -> str:
        return (
            f"observation_dim={self.observation_dim}, action_dim={self.action_dim}, "
            f"num_members={self.num_members}, hidden_sizes={self.hidden_sizes}, prior_scale={self.prior_scale}"
            + (f", prior_bias_draw={self.prior_bias_draw!r}" if self.has_prior else "")
        )
