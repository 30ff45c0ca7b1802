"""The classifier ensemble, computed faster: the same numbers as :class:`~torchrl_reset.EnsembleValueOperator`.

What is done differently, and why (each measured on the 2-core CPU machines, see ``docs/benchmarks.md``):

- products: ``baddbmm`` with the bias folded in; a one-wide output layer as row-wise dot products
  (a batched product with one output column is several times slower on CPU); the rows of each
  member cut into blocks so that a batched product divides evenly over the CPU threads;
- without gradients (the trigger, the labels), trained and prior members run as one stack of 2K;
- :meth:`FastEnsembleValueOperator.paired_logits`: the classifier loss's pairs and the actor loss's
  pairs share the state part of every member (layer 0 and the state half of layer 1, almost all the
  work), and the priors' state part of the fixed success examples is computed once and kept.
"""
from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase

from ..ensemble import EnsembleValueOperator, with_prior

__all__ = ["FastEnsembleValueOperator", "members_trunk", "members_head"]


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


def members_trunk(x: torch.Tensor, weights: list[torch.Tensor], biases: list[torch.Tensor]) -> torch.Tensor:
    """The state part of M stacked members: layer 0 and the state half of layer 1 with its bias, before the
    action joins. ``x``: ``[N, d]`` shared by the members, or ``[M, N, d]`` one set of rows per member.
    Returns ``[M, N, h1]``."""
    if x.dim() == 2:
        x = x.unsqueeze(0).expand(weights[0].shape[0], *x.shape)
    hidden = torch.baddbmm(biases[0].unsqueeze(-2), x, weights[0]).relu_()
    return _members_linear(hidden, weights[1], biases[1])


def members_head(
    trunk: torch.Tensor,
    action: torch.Tensor,
    weights: list[torch.Tensor],
    biases: list[torch.Tensor],
    action_weight: torch.Tensor,
    *,
    overwrite: bool = False,
) -> torch.Tensor:
    """The rest of M members from their trunk ``[M, N, h1]`` and the actions, ``[N, a]`` shared or
    ``[M, N, a]``: ``[M, N]`` logits.

    ``overwrite=True`` adds the action part into ``trunk`` itself (no copy of it): only for a trunk that
    nothing reads afterwards (autograd does not keep the trunk for backward).
    """
    if action.dim() == 2:
        action = action.unsqueeze(0).expand(trunk.shape[0], *action.shape)
    hidden = trunk.baddbmm_(action, action_weight) if overwrite else torch.baddbmm(trunk, action, action_weight)
    for i in range(2, len(weights)):
        hidden = _members_linear(hidden.relu_(), weights[i], biases[i])
    return hidden.squeeze(-1)


class _PriorStateCache:
    """The priors' state part (``FastEnsembleValueOperator._trunk``) for states kept in numbered slots.

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
            return FastEnsembleValueOperator._trunk(obs, weights, biases)
        source = tuple((t.data_ptr(), t._version) for t in (*weights[:2], *biases[:2]))
        self._fit(obs, high + 1, members, width, source)
        stale = (self.states[slots] != obs).any(-1)  # NaN (never filled) compares unequal
        if bool(stale.any()):
            # The whole batch, not only its new rows: a matrix product's rows can come out a few
            # bits different with the number of rows (BLAS kernels for very few rows), and the
            # kept values must not depend on how earlier batches were drawn (a resumed run starts
            # with nothing kept and must reproduce the uninterrupted one).
            trunk = FastEnsembleValueOperator._trunk(obs, weights, biases)
            rows = stale.nonzero().squeeze(-1)
            where = slots[rows]
            self.trunks[:, where] = trunk[:, rows]
            self.states[where] = obs[rows]
            return trunk
        return self.trunks[:, slots]


class FastEnsembleValueOperator(EnsembleValueOperator):
    """:class:`~torchrl_reset.EnsembleValueOperator` with fused, thread-balanced products.

    The same parameters, buffers, keys and state dict (a checkpoint of one loads into the other);
    logits agree to float32 rounding (``tests/test_accel.py`` pins the two). Adds
    :meth:`paired_logits`, which :class:`~torchrl_reset.accel.FastRCELoss` uses.
    """

    def __init__(self, *args, **kwargs) -> None:
        self._prior_cache = _PriorStateCache()
        super().__init__(*args, **kwargs)

    def reset_parameters(self) -> None:
        self._prior_cache.clear()
        super().reset_parameters()

    def __setstate__(self, state) -> None:
        super().__setstate__(state)
        if "_prior_cache" not in self.__dict__:
            self._prior_cache = _PriorStateCache()

    _trunk = staticmethod(members_trunk)
    _head = staticmethod(members_head)

    @classmethod
    def members_forward(
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

    def logits(
        self, observation: torch.Tensor, action: torch.Tensor, params: TensorDictBase | None = None
    ) -> torch.Tensor:
        """:meth:`EnsembleValueOperator.logits`, with the fused products; without gradients trained and
        prior members run as one stack of 2K."""
        batch = observation.shape[:-1]
        obs, act = self._check_inputs(observation, action)
        k = self.num_members
        weights, biases, action_weight = self.layer_tensors(params)
        if not self.has_prior:
            out = self.members_forward(obs, act, weights, biases, action_weight)
        elif torch.is_grad_enabled():
            # Separate prior pass: autograd then computes no weight gradients for the frozen half.
            out = self.members_forward(obs, act, weights, biases, action_weight)
            p_weights, p_biases, p_action_weight = self.layer_tensors(params, "prior_")
            prior = self.members_forward(obs, act, p_weights, p_biases, p_action_weight)
            out = with_prior(out, prior, self.prior_scale)
        else:
            # Without gradients, trained and prior members run as one stack of 2K.
            p_weights, p_biases, p_action_weight = self.layer_tensors(params, "prior_")
            stacked = self.members_forward(
                obs,
                act,
                [torch.cat(pair) for pair in zip(weights, p_weights)],
                [torch.cat(pair) for pair in zip(biases, p_biases)],
                torch.cat([action_weight, p_action_weight]),
            )
            out = with_prior(stacked[:k], stacked[k:], self.prior_scale)
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
            policy_action (Tensor or None): ``[N - start, action_dim]``, actions for the last rows; None:
                no policy pairs (the second result is None).
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
        with_policy = policy_action is not None
        if with_policy:
            policy_obs, policy_act = self._check_inputs(observation[start:], policy_action)
        weights, biases, action_weight = self.layer_tensors(params)
        trunk = self._trunk(obs, weights, biases)
        if with_policy:
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
            if with_policy:  # the policy's prior first: the replay rows' prior then reuses the trunk's memory
                policy = with_prior(policy, self._head(rest, policy_act, *p_layers), self.prior_scale)
            with torch.no_grad():
                if use_cache:
                    prior = torch.cat([
                        self._head(kept, act[:start], *p_layers, overwrite=True),
                        self._head(prior_trunk, act[start:], *p_layers, overwrite=True),
                    ], 1)
                else:
                    prior = self._head(prior_trunk, act, *p_layers, overwrite=True)
            out = with_prior(out, prior, self.prior_scale)
        return out.transpose(0, 1), policy.transpose(0, 1) if with_policy else None
