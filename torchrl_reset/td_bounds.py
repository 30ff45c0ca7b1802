"""TD(0) targets held to the values that bounded rewards allow (an option for DDPG critics, not the paper's).

With rewards in ``[low, high]`` and discount ``gamma < 1`` every true value lies in
``[low, high] / (1 - gamma)``. A DDPG critic can still drift outside that range: each target takes the
actor's action, which the critic scores slightly above the replayed one, and over a 1 / (1 - gamma)
horizon that bias adds up (``results/100000/README.md`` shows LNT's reset critics at -32 to 425 where
the true values lie in [0, 100]). The authors' DDPG code can clip every target to that range when
reward bounds are configured; :class:`BoundedTD0Estimator` does the same for torchrl's losses.
"""
from __future__ import annotations

import math

import torch
from torchrl.objectives.value import TD0Estimator

__all__ = ["BoundedTD0Estimator", "bound_td0_targets"]


def _bounds(reward_bounds, gamma: float) -> tuple[float, float]:
    try:
        low, high = (float(v) for v in reward_bounds)
    except (TypeError, ValueError):
        raise ValueError(f"reward_bounds must be a pair of numbers (low, high); got {reward_bounds!r}.") from None
    if not (math.isfinite(low) and math.isfinite(high)) or low >= high:
        raise ValueError(f"reward_bounds must be finite with low < high; got ({low}, {high}).")
    if not 0.0 <= gamma < 1.0:
        raise ValueError(f"bounded TD targets need a discount in [0, 1); got gamma = {gamma}.")
    return low / (1.0 - gamma), high / (1.0 - gamma)


class BoundedTD0Estimator(TD0Estimator):
    """torchrl's :class:`~torchrl.objectives.value.TD0Estimator` with every target clipped to
    ``[low, high] / (1 - gamma)``, the values rewards in ``reward_bounds = (low, high)`` allow.

    Args:
        reward_bounds (tuple of float): the least and the greatest reward.
        gamma (float): the discount, below 1.
        value_network: as for ``TD0Estimator``; the other keyword arguments too.

    Examples:
        >>> import torch
        >>> from torchrl_reset.td_bounds import BoundedTD0Estimator
        >>> est = BoundedTD0Estimator(reward_bounds=(-1.0, 1.0), gamma=0.5, value_network=None)
        >>> est.bounds
        (-2.0, 2.0)
    """

    def __init__(self, *, reward_bounds, gamma: float, value_network, **kwargs):
        gamma = float(gamma)
        self.bounds = _bounds(reward_bounds, gamma)
        super().__init__(gamma=gamma, value_network=value_network, **kwargs)

    def value_estimate(self, tensordict, target_params=None, next_value=None, **kwargs) -> torch.Tensor:
        target = super().value_estimate(tensordict, target_params=target_params, next_value=next_value, **kwargs)
        return target.clamp(*self.bounds)


def bound_td0_targets(loss, reward_bounds) -> BoundedTD0Estimator:
    """Gives ``loss`` (a DDPG-style loss with a TD(0) estimator, for example after
    ``loss.make_value_estimator(gamma=...)``) a :class:`BoundedTD0Estimator` with the same discount and
    keys."""
    current = loss.value_estimator
    if type(current) is not TD0Estimator:
        raise TypeError(f"bound_td0_targets needs the loss's TD(0) estimator; it has {type(current).__name__}.")
    keys = loss.tensor_keys
    estimator = BoundedTD0Estimator(reward_bounds=reward_bounds, gamma=float(current.gamma),
                                    value_network=loss.actor_critic)
    estimator.set_keys(value=keys.state_action_value, reward=keys.reward, done=keys.done, terminated=keys.terminated)
    loss._value_estimator = estimator  # as torchrl's own dispatch stores it (the property's setter would register a module)
    return estimator
