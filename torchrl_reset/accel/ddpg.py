"""torchrl's DDPG loss with its per-call bookkeeping taken out (the same losses, computed directly)."""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torch.func import functional_call
from torchrl.objectives import DDPGLoss
from torchrl.objectives.utils import distance_loss
from torchrl.objectives.value import TD0Estimator
from ..td_bounds import BoundedTD0Estimator

__all__ = ["DirectDDPGLoss"]


def _flat(params: TensorDictBase) -> dict[str, torch.Tensor]:
    """``{"module.0.weight": tensor, ...}``: a loss module's parameter tensordict in module naming."""
    return {".".join(key) if isinstance(key, tuple) else key: value for key, value in params.items(True, True)}


def _holds(module: nn.Module, params: TensorDictBase) -> bool:
    """Whether ``module``'s own parameters are those in ``params`` (then it runs on them unswapped)."""
    own = {id(p) for p in module.parameters()}
    return all(id(p) in own for p in params.parameters())  # TensorDictParams is a module: its parameters


class DirectDDPGLoss(DDPGLoss):
    """:class:`~torchrl.objectives.DDPGLoss` whose ``forward`` computes the same losses with less bookkeeping.

    Construction, parameters, target parameters, keys, :meth:`make_value_estimator` and
    :class:`~torchrl.objectives.SoftUpdate` are torchrl's, unchanged: it is a drop-in replacement.
    Only the per-call work differs. torchrl's ``forward`` swaps parameter sets into the networks
    with ``TensorDict.to_module`` four times per call, copies the input tensordict for each
    network and goes through the value estimator's generic ``step_mdp``; on a batch-64 update of
    400-300 networks that bookkeeping is a large share of the time (``benchmarks/bench_updates.py``
    times the recipe's forward update both ways). Here the networks run on small tensordicts of
    the entries they read, their own live parameters need no swap, and the target and detached
    parameter sets go in through :func:`torch.func.functional_call`.

    The direct path covers the recipe's configuration: the TD(0) value estimator (or its bounded
    form, :class:`~torchrl_reset.BoundedTD0Estimator`, whose clipping it applies) without reward
    standardisation or ``steps_to_next_obs``, no priority weights, and networks that hold the
    loss's trained parameters themselves (as torchrl's conversion leaves them). Anything else
    (another estimator, prioritized replay weights in the batch) runs torchrl's own ``forward``. Outputs are
    torchrl's: ``loss_actor``, ``loss_value`` and the metadata entries (``td_error``,
    ``pred_value``, ``target_value`` and their maxima), and the priority entry written into the
    input.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.modules import ValueOperator
        >>> from torchrl_reset.accel import DirectDDPGLoss
        >>> actor = TensorDictModule(torch.nn.Linear(3, 2), ["observation"], ["action"])
        >>> class Critic(torch.nn.Module):
        ...     def __init__(self):
        ...         super().__init__()
        ...         self.net = torch.nn.Linear(5, 1)
        ...     def forward(self, observation, action):
        ...         return self.net(torch.cat([observation, action], -1))
        >>> loss = DirectDDPGLoss(actor, ValueOperator(Critic(), in_keys=["observation", "action"]), delay_actor=True)
        >>> batch = TensorDict(observation=torch.randn(4, 3), action=torch.randn(4, 2), next=TensorDict(
        ...     observation=torch.randn(4, 3), reward=torch.randn(4, 1), done=torch.zeros(4, 1, dtype=torch.bool),
        ...     terminated=torch.zeros(4, 1, dtype=torch.bool), batch_size=[4]), batch_size=[4])
        >>> out = loss(batch)
        >>> sorted(out.keys())[:2]
        ['loss_actor', 'loss_value']
    """

    def _direct(self, tensordict: TensorDictBase) -> bool:
        estimator = self.value_estimator
        return (
            type(estimator) in (TD0Estimator, BoundedTD0Estimator)
            and not estimator.average_rewards
            and self._maybe_get_priority_weight(tensordict) is None
            and estimator.tensor_keys.steps_to_next_obs not in tensordict.keys(True)
            and _holds(self.actor_network, self.actor_network_params)
            and _holds(self.value_network, self.value_network_params)
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        if not self._direct(tensordict):
            return super().forward(tensordict)
        keys = self.tensor_keys
        actor, value = self.actor_network, self.value_network
        actor_keys = list(self.actor_in_keys)
        batch = tensordict.batch_size

        # value loss: the critic on the replay pairs (its live parameters), against the TD(0)
        # target from the target actor and critic on the next states
        pairs = TensorDict({key: tensordict.get(key).detach() for key in value.in_keys}, batch_size=batch)
        pred_val = value(pairs).get(keys.state_action_value).squeeze(-1)
        next_td = tensordict.get("next")
        with torch.no_grad():
            following = TensorDict({key: next_td.get(key) for key in actor_keys}, batch_size=next_td.batch_size)
            following = functional_call(actor, _flat(self.target_actor_network_params), (following,))
            following = functional_call(value, _flat(self.target_value_network_params), (following,))
            next_value = following.get(keys.state_action_value)
            reward = next_td.get(keys.reward)
            terminated = next_td.get(keys.terminated, None)
            if terminated is None:
                terminated = next_td.get(keys.done)
            if not next_value.shape == reward.shape == terminated.shape:
                raise RuntimeError(
                    f"DirectDDPGLoss: the next value {tuple(next_value.shape)}, reward {tuple(reward.shape)} and "
                    f"terminated {tuple(terminated.shape)} entries must have the same shape."
                )
            gamma = self.value_estimator.gamma.to(reward.device)
            target_value = (reward + gamma * (~terminated).int() * next_value).squeeze(-1)
            bounds = getattr(self.value_estimator, "bounds", None)  # BoundedTD0Estimator: the reward bounds' values
            if bounds is not None:
                target_value = target_value.clamp(*bounds)
        loss_value = self._reduce_loss(distance_loss(pred_val, target_value, loss_function=self.loss_function),
                                       tensordict=tensordict)
        td_error = (pred_val - target_value).pow(2).detach()
        if tensordict.device is not None:
            td_error = td_error.to(tensordict.device)
        tensordict.set(keys.priority, td_error, inplace=True)

        # actor loss: the critic, its parameters held fixed, on the actor's actions
        acting = TensorDict({key: tensordict.get(key).detach() for key in actor_keys}, batch_size=batch)
        for key in self.value_exclusive_keys:  # critic inputs the actor does not write
            acting.set(key, tensordict.get(key).detach())
        acting = actor(acting)
        held = {name: param.detach() for name, param in value.named_parameters()}
        acting = functional_call(value, held, (acting,), strict=False)
        loss_actor = self._reduce_loss(-acting.get(keys.state_action_value).squeeze(-1), tensordict=tensordict)

        with torch.no_grad():
            metadata = {
                "td_error": td_error,
                "pred_value": pred_val.detach(),
                "target_value": target_value,
                "target_value_max": target_value.max(),
                "pred_value_max": pred_val.detach().max(),
            }
        return TensorDict({"loss_actor": loss_actor, "loss_value": loss_value, **metadata}, batch_size=[])
