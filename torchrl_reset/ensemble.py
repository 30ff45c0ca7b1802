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
    "reduce_members",
    "success_classifier",
    "success_probability",
]

MEMBER_REDUCTIONS = ("mean", "min", "max")


def success_classifier(logits: torch.Tensor) -> torch.Tensor:
    """The classifier value ``C = sigmoid(logit)``, in [0, 1]."""
    return torch.sigmoid(logits)


def success_probability(logits: torch.Tensor) -> torch.Tensor:
    """The classifier ratio ``p = C / (1 - C)`` with ``C`` clipped to [0, 0.5] first.

    ``sigmoid(l) / (1 - sigmoid(l)) = exp(l)`` and ``C <= 0.5`` is ``l <= 0``, so the clipped ratio is
    ``exp(min(l, 0))``: the same number, computed without cancellation. The result lies in [0, 1].
    """
    return torch.exp(logits.clamp(max=0.0))


def reduce_members(values: torch.Tensor, reduction: str = "mean") -> torch.Tensor:
    """Reduces the trailing ensemble-member dimension with ``"mean"``, ``"min"`` or ``"max"``."""
    if reduction == "mean":
        return values.mean(-1)
    if reduction == "min":
        return values.amin(-1)
    if reduction == "max":
        return values.amax(-1)
    raise ValueError(f"reduction must be one of {MEMBER_REDUCTIONS}, got {reduction!r}.")


def _row_split(members: int, rows: int, device: torch.device) -> int:
    """How many row blocks to cut each member's rows into so that a batched product divides evenly.

    On CPU, a batched matrix product shares its batch entries out among the threads; with K = 5
    members on 2 threads one thread does 3 products and the other 2. Cutting every member's rows in
    ``s`` blocks makes ``K * s`` entries that divide evenly (at least 64 rows a block). Products
    handed to oneDNN (``torch.backends.mkldnn.matmul.fp32_precision = "bf16"``) divide each
    product over the threads themselves: there the cut only costs copies (measured 1.1 ms slower
    per reset update on 2 cores), so it is left out.
    """
    if device.type != "cpu" or torch.compiler.is_compiling() or torch.backends.mkldnn.matmul.fp32_precision == "bf16":
        return 1
    threads = torch.get_num_threads()
    if threads <= 1 or members % threads == 0 or members >= 4 * threads:
        return 1
    split = threads // math.gcd(members, threads)
    return split if rows % split == 0 and rows // split >= 64 else 1


def _members_linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``x[i] @ weight[i] + bias[i]`` for every member ``i``: [M, N, d] x [M, d, h] -> [M, N, h].

    A one-wide output (the logit layer) is computed as row-wise dot products: a batched matrix
    product with a single output column runs several times slower on CPU, forward and backward.
    """
    if weight.shape[-1] == 1:
        return (torch.linalg.vecdot(x, weight.transpose(-1, -2)) + bias).unsqueeze(-1)
    members, rows, width = x.shape
    split = _row_split(members, rows, x.device)
    # the bias added after the product: measured faster than baddbmm's broadcast copy of it into
    # the output for these wide layers (0.3 ms on a [10, 512, 400] x [10, 400, 300] product)
    if split == 1:
        return torch.bmm(x, weight).add_(bias.unsqueeze(-2))
    blocks = members * split
    out = torch.bmm(
        x.reshape(blocks, rows // split, width),
        weight.unsqueeze(1).expand(members, split, *weight.shape[1:]).reshape(blocks, *weight.shape[1:]),
    )
    return out.view(members, rows, -1).add_(bias.unsqueeze(-2))


class _PriorStateCache:
    """The priors' state part (``EnsembleValueOperator._trunk``) for states kept in numbered slots.

    The priors never train, so their state part is a fixed function of the state: for a fixed set
    of states sampled again and again (the success examples) it is computed once per state. Each
    slot remembers the state it was computed for, and the whole cache the prior tensors it was
    computed with (their identity and in-place version), so a slot whose state changed (a buffer
    that overwrote it) or priors that were reloaded are recomputed, never read stale.
    """

    max_slots = 1 << 14  # about 100 MB at K = 5, 300 units; slots past it are computed each time

    def __init__(self) -> None:
        self.states: torch.Tensor | None = None  # NaN in a slot never filled: it matches no state
        self.trunks: torch.Tensor | None = None
        self.source: tuple | None = None

    def clear(self) -> None:
        self.states = self.trunks = self.source = None

    def _fit(self, obs: torch.Tensor, size: int, members: int, width: int, source: tuple) -> None:
        fresh = (
            self.states is None
            or self.source != source
            or self.states.shape[-1] != obs.shape[-1]
            or self.states.dtype != obs.dtype
            or self.states.device != obs.device
            or self.trunks.shape[0] != members
            or self.trunks.shape[-1] != width
        )
        if fresh:
            self.clear()
            capacity = 0
        else:
            capacity = self.states.shape[0]
        if size <= capacity:
            return
        new_capacity = min(self.max_slots, max(256, 1 << (size - 1).bit_length()))
        states = obs.new_full((new_capacity, obs.shape[-1]), float("nan"))
        trunks = obs.new_empty(members, new_capacity, width)
        if capacity:
            states[:capacity] = self.states
            trunks[:, :capacity] = self.trunks
        self.states, self.trunks, self.source = states, trunks, source

    def lookup(self, obs: torch.Tensor, slots: torch.Tensor, weights: list[torch.Tensor], biases: list[torch.Tensor]) -> torch.Tensor:
        """The prior trunk [M, N, h1] of ``obs`` [N, d], whose rows sit in ``slots`` [N]."""
        members, width = weights[1].shape[0], weights[1].shape[-1]
        low, high = (int(v) for v in torch.aminmax(slots)) if slots.numel() else (-1, -1)
        if low < 0 or high >= self.max_slots:
            return EnsembleValueOperator._trunk(obs, weights, biases)
        source = tuple((t.data_ptr(), t._version) for t in (*weights[:2], *biases[:2]))
        self._fit(obs, high + 1, members, width, source)
        stale = (self.states[slots] != obs).any(-1)  # NaN (never filled) compares unequal
        if bool(stale.any()):
            # The whole batch, not only its new rows: a matrix product's rows can come out a few
            # bits different with the number of rows (BLAS kernels for very few rows), and the
            # kept values must not depend on how earlier batches were drawn (a resumed run starts
            # with nothing kept and must reproduce the uninterrupted one).
            trunk = EnsembleValueOperator._trunk(obs, weights, biases)
            rows = stale.nonzero().squeeze(-1)
            where = slots[rows]
            self.trunks[:, where] = trunk[:, rows]
            self.states[where] = obs[rows]
            return trunk
        return self.trunks[:, slots]


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
    batched matrix products (no Python loop over members).

    Trainable weights use Xavier-uniform initialisation and zero biases (method.md section 5).

    Args:
        observation_dim (int): size of the observation (the sum of the sizes of all observation
            keys when several are given).
        action_dim (int): size of the action.

    Keyword Args:
        num_members (int): the ensemble size K. Defaults to 5.
        hidden_sizes (sequence of int): hidden layer sizes. Defaults to ``(400, 300)``.
        prior_scale (float): the prior scale beta. ``0`` disables the priors. Defaults to 3.
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
        self._prior_cache = _PriorStateCache()
        self.reset_parameters()

    @property
    def has_prior(self) -> bool:
        return self.prior_scale > 0

    def reset_parameters(self) -> None:
        """Xavier-uniform weights and zero biases for the trained part; a fresh random prior."""
        sizes_in = (self.observation_dim, *self.hidden_sizes)
        sizes_out = (*self.hidden_sizes, 1)
        self._prior_cache.clear()
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
                        bound = 1.0 / math.sqrt(fan_in)
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
    def _trunk(obs: torch.Tensor, weights: list[torch.Tensor], biases: list[torch.Tensor]) -> torch.Tensor:
        """The state-only part of M stacked members on shared [N, d] observations: layer 0 and the
        state half of layer 1 with its bias, before the action joins. Returns [M, N, h1]."""
        members = weights[0].shape[0]
        x = obs.unsqueeze(0).expand(members, *obs.shape)
        hidden = torch.baddbmm(biases[0].unsqueeze(-2), x, weights[0]).relu_()
        return _members_linear(hidden, weights[1], biases[1])

    @staticmethod
    def _head(
        trunk: torch.Tensor,
        action: torch.Tensor,
        weights: list[torch.Tensor],
        biases: list[torch.Tensor],
        action_weight: torch.Tensor,
        *,
        overwrite: bool = False,
    ) -> torch.Tensor:
        """The rest of M members from their trunk output [M, N, h1] and shared [N, a] actions: [M, N] logits.

        ``overwrite=True`` adds the action part into ``trunk`` itself (no copy of it): only for a
        trunk that nothing reads afterwards (autograd does not keep the trunk for backward).
        """
        members = trunk.shape[0]
        actions = action.unsqueeze(0).expand(members, *action.shape)
        if overwrite:
            hidden = trunk.baddbmm_(actions, action_weight)
        else:
            hidden = torch.baddbmm(trunk, actions, action_weight)
        for i in range(2, len(weights)):
            hidden = _members_linear(hidden.relu_(), weights[i], biases[i])
        return hidden.squeeze(-1)

    @classmethod
    def _members_forward(
        cls,
        obs: torch.Tensor,
        action: torch.Tensor,
        weights: list[torch.Tensor],
        biases: list[torch.Tensor],
        action_weight: torch.Tensor,
    ) -> torch.Tensor:
        """Runs M stacked members on the same [N, *] inputs; returns [M, N] logits."""
        overwrite = not torch.is_grad_enabled()
        return cls._head(cls._trunk(obs, weights, biases), action, weights, biases, action_weight, overwrite=overwrite)

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
        """Per-member logits for a batch of (observation, action) pairs.

        Args:
            observation (Tensor): ``[*batch, observation_dim]``.
            action (Tensor): ``[*batch, action_dim]``.
            params (TensorDictBase, optional): the parameters and buffers to use instead of the
                module's own (for instance a loss module's target copy).

        Returns:
            ``[*batch, K]`` logits ``f_i + beta * g_i``.
        """
        batch = observation.shape[:-1]
        obs, act = self._check_inputs(observation, action)
        k = self.num_members
        weights, biases, action_weight = self.layer_tensors(params)
        if not self.has_prior:
            out = self._members_forward(obs, act, weights, biases, action_weight)
        elif torch.is_grad_enabled():
            # Separate prior pass: autograd then computes no weight gradients for the frozen half.
            out = self._members_forward(obs, act, weights, biases, action_weight)
            p_weights, p_biases, p_action_weight = self.layer_tensors(params, "prior_")
            prior = self._members_forward(obs, act, p_weights, p_biases, p_action_weight)
            out = out + self.prior_scale * prior
        else:
            # Without gradients, trained and prior members run as one stack of 2K.
            p_weights, p_biases, p_action_weight = self.layer_tensors(params, "prior_")
            stacked = self._members_forward(
                obs,
                act,
                [torch.cat(pair) for pair in zip(weights, p_weights)],
                [torch.cat(pair) for pair in zip(biases, p_biases)],
                torch.cat([action_weight, p_action_weight]),
            )
            out = stacked[:k] + self.prior_scale * stacked[k:]
        return out.transpose(0, 1).reshape(*batch, k)

    def paired_logits(
        self,
        observation: torch.Tensor,
        action: torch.Tensor,
        policy_action: torch.Tensor,
        start: int,
        params: TensorDictBase | None = None,
        slots: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Logits of ``(observation, action)`` and of ``(observation[start:], policy_action)`` in one pass.

        The state part of every member (layer 0 and the state half of layer 1: almost all of the
        work) is computed once for both. The first result carries gradient to the trained
        parameters (as :meth:`logits`); the second carries gradient to ``policy_action`` only, the
        classifier held fixed: what an actor loss needs.

        Args:
            observation (Tensor): ``[N, observation_dim]``.
            action (Tensor): ``[N, action_dim]``.
            policy_action (Tensor): ``[N - start, action_dim]``, actions for the last rows.
            start (int): the first row the policy actions belong to.
            params (TensorDictBase, optional): as in :meth:`logits`.
            slots (Tensor, optional): ``[start]`` integer slots of the first ``start`` rows in a
                store of fixed states (such as :class:`~torchrl_reset.InitialStateBuffer`'s
                ``"index"``). The priors' state part of those rows is then computed once per state
                and kept: the same numbers, without the repeated work. Ignored under
                ``torch.compile``.

        Returns:
            ``[N, K]`` and ``[N - start, K]`` logits.
        """
        obs, act = self._check_inputs(observation, action)
        policy_obs, policy_act = self._check_inputs(observation[start:], policy_action)
        weights, biases, action_weight = self.layer_tensors(params)
        trunk = self._trunk(obs, weights, biases)
        held = [w.detach() for w in weights], [b.detach() for b in biases], action_weight.detach()
        policy = self._head(trunk[:, start:].detach(), policy_act, *held)
        # after the policy's head: this one may add into the trunk in place
        out = self._head(trunk, act, weights, biases, action_weight, overwrite=True)
        if self.has_prior:
            p_weights, p_biases, p_action_weight = self.layer_tensors(params, "prior_")
            p_layers = p_weights, p_biases, p_action_weight
            use_cache = slots is not None and start > 0 and not torch.compiler.is_compiling()
            if use_cache and (slots.shape != (start,) or slots.dtype.is_floating_point or slots.dtype == torch.bool):
                raise ValueError(
                    f"slots must be integers, one per row before start ({start}); got shape {tuple(slots.shape)}, {slots.dtype}."
                )
            with torch.no_grad():
                if use_cache:
                    kept = self._prior_cache.lookup(obs[:start], slots.to(obs.device), p_weights, p_biases)
                    prior_trunk = self._trunk(obs[start:], p_weights, p_biases)
                else:
                    prior_trunk = self._trunk(obs, p_weights, p_biases)
            rest = prior_trunk if use_cache else prior_trunk[:, start:]
            # the policy's prior first: the replay rows' prior then reuses the trunk's memory
            policy = policy + self.prior_scale * self._head(rest, policy_act, *p_layers)
            with torch.no_grad():
                if use_cache:
                    prior = torch.cat([
                        self._head(kept, act[:start], *p_layers, overwrite=True),
                        self._head(prior_trunk, act[start:], *p_layers, overwrite=True),
                    ], 1)
                else:
                    prior = self._head(prior_trunk, act, *p_layers, overwrite=True)
            out = out + self.prior_scale * prior
        return out.transpose(0, 1), policy.transpose(0, 1)

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
        )
