"""What keeps a bounded actor's output from sticking at the edge of its action box.

A DDPG-style actor ends in ``tanh``: once its pre-activation ``u`` lies deep in the tanh's flat tail, the
gradient that would bring it back is multiplied by ``1 - tanh(u)^2`` and never arrives. These are the
remedies a reset actor (or any bounded actor) can take, each usable on its own:

- :class:`InvertingGradientHead` (Hausknecht & Stone, ICLR 2016): no tanh; the actor's output is the
  action in the box's normalised coordinates, clipped for acting, and the action gradient is scaled by the
  distance to the bound it pushes towards (and reversed beyond it), so the output never leaves the box for
  long and a push back inside is never damped;
- :func:`actor_penalties`: ``c_u mean(u^2)`` on the pre-activation and ``c_a mean(a_n^2)`` on the normalised
  action (OpenAI HER's ``action_l2``);
- :class:`EntropyBonus`: for a stochastic tanh-Gaussian actor (RCE's original, Eysenbach et al. 2021),
  ``alpha * mean(log pi(a|s))`` with ``alpha`` fixed or learned against a target entropy (SAC's temperature).

:func:`saturation` measures the trap: the share of action components beyond 0.99 of the bound and the mean
``|u|``.
"""
from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

__all__ = ["InvertingGradients", "InvertingGradientHead", "actor_penalties", "EntropyBonus", "saturation",
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


class EntropyBonus(nn.Module):
    """The entropy term of a stochastic actor's loss, ``alpha * mean(log pi(a|s))`` (``a`` a reparameterised
    sample), with ``alpha`` fixed (``alpha=0.0001``, RCE's) or, with ``target_entropy``, learned as SAC learns
    its temperature: ``log alpha`` descends ``-log alpha * mean(log pi + target_entropy)`` (detached), which
    raises alpha while the policy's entropy is below the target and lowers it above.

    Args:
        alpha (float): the fixed coefficient, or the learned one's initial value.
        target_entropy (float, optional): the entropy the learned alpha aims for (SAC: ``-dim(A)``); None
            keeps alpha fixed.

    Examples:
        >>> import torch
        >>> bonus = EntropyBonus(alpha=0.5)
        >>> round(float(bonus(torch.tensor([-1.0, -3.0]))), 4)  # 0.5 * mean(log pi)
        -1.0
    """

    def __init__(self, alpha: float, target_entropy: float | None = None) -> None:
        super().__init__()
        if not alpha > 0:
            raise ValueError(f"alpha must be positive, got {alpha!r}.")
        self.target_entropy = None if target_entropy is None else float(target_entropy)
        log_alpha = torch.tensor(math.log(alpha))
        if self.learned:
            self.log_alpha = nn.Parameter(log_alpha)
        else:
            self.register_buffer("log_alpha", log_alpha)

    @property
    def learned(self) -> bool:
        return self.target_entropy is not None

    @property
    def alpha(self) -> float:
        return float(self.log_alpha.detach().exp())

    def forward(self, log_prob: torch.Tensor) -> torch.Tensor:
        """The actor's entropy term (gradient to the actor only) plus, when alpha is learned, the temperature's
        loss (gradient to ``log_alpha`` only)."""
        term = self.log_alpha.detach().exp() * log_prob.mean()
        if self.learned:
            term = term - (self.log_alpha * (log_prob.detach() + self.target_entropy)).mean()
        return term


def saturation(normalised_action: torch.Tensor, preactivation: torch.Tensor) -> tuple[int, int, float]:
    """``(saturated, components, sum |u|)``: how many action components (normalised coordinates) lie beyond
    :data:`SATURATION_LEVEL` of the bound, out of how many, and the sum of ``|u|`` over them."""
    return (int((normalised_action.abs() > SATURATION_LEVEL).sum()), normalised_action.numel(),
            float(preactivation.abs().sum()))
