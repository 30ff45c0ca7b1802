"""DDPG on an ensemble of K Q-functions and one actor, as the authors' DDPG class runs K critics.

Leave No Trace's reset agent (and LNT-sparse's) is DDPG whose critic is an ensemble of K Q-functions, and
whose trigger takes their minimum. torchrl's ``DDPGLoss`` run on an ensemble value network (the project's
default LNT) trains every member on one shared batch and gives the actor the mean of the K members' values.
The authors' DDPG class with K critics (``algo/ddpg.py``, ``algo/memory.py`` of their release) does neither,
and the difference bears on how far apart the members are, hence on how pessimistic their minimum is:

- **independent batches**: each member's TD loss is on a batch of its own (``buffer.sample(batch_size,
  num_batches=K)``); here the input is then ``[K, B]``, member ``k``'s rows at index ``k``;
- **one member per actor row**: the actor is trained on ``B`` rows drawn with replacement from the ``K * B``
  rows of the critics' batches, each row's action gradient from the member whose batch it came from; with a
  shared batch ``[B]``, each row's member is drawn uniformly.

Each member ``k``'s TD(0) target is ``r + gamma * (1 - terminated) * Q'_k(s', pi'(s'))``, clipped to
``[low, high] / (1 - gamma)`` when ``reward_bounds`` is given (the release's ``reward_lower/upper``); the
value loss is the mean over members and rows of ``(Q_k(s, a) - y_k)^2`` (torchrl's ``DDPGLoss`` with its l2
distance); the actor loss is ``-mean Q(s, pi(s))`` over its rows.
"""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import LossModule

from .ensemble import EnsembleValueOperator
from .stochastic_actor import StochasticActorMixin

__all__ = ["EnsembleDDPGLoss"]


class EnsembleDDPGLoss(StochasticActorMixin, LossModule):
    """DDPG on an :class:`~torchrl_reset.EnsembleValueOperator` of K Q-functions, with the release's ensemble
    semantics as options (see the module's docstring).

    Args:
        actor_network (TensorDictModuleBase): the policy, reading the observation keys and writing ``"action"``.
        value_network (EnsembleValueOperator): K Q-functions, ``[*batch, K]`` values.

    Keyword Args:
        gamma (float): the discount. Defaults to 0.99.
        independent_batches (bool): the input is ``[K, B]``, member ``k``'s batch at index ``k``. Defaults to False.
        member_actor_gradient (bool): each actor row's value from one member (see above); False: the mean of
            the K members' values (torchrl's ``DDPGLoss``). Defaults to False.
        reward_bounds (tuple, optional): ``(low, high)`` of the rewards; the targets are clipped to
            ``[low, high] / (1 - gamma)``.
        reward_key (str): the reward entry under ``"next"``, ``[*batch, K]`` or ``[*batch, 1]``. Defaults to ``"reward"``.
        alpha_init, fixed_alpha, target_entropy, min_alpha, max_alpha, action_spec: a stochastic actor's
            temperature, as :class:`~torchrl_reset.RCELoss` (its ``log pi`` from a sample of its own on the
            whole input).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torch import nn
        >>> from torchrl_reset import EnsembleValueOperator
        >>> actor = TensorDictModule(nn.Sequential(nn.Linear(3, 2), nn.Tanh()), ["observation"], ["action"])
        >>> q = EnsembleValueOperator(3, 2, num_members=4, hidden_sizes=(8, 8), prior_scale=0.0,
        ...                           out_keys=["state_action_value"])
        >>> loss = EnsembleDDPGLoss(actor, q, independent_batches=True, member_actor_gradient=True)
        >>> K, B = 4, 5
        >>> state = lambda: torch.randn(K, B, 3)
        >>> batch = TensorDict(observation=state(), action=torch.rand(K, B, 2),
        ...                    next=TensorDict(observation=state(), reward=torch.rand(K, B, 1),
        ...                                    terminated=torch.zeros(K, B, 1, dtype=torch.bool), batch_size=[K, B]),
        ...                    batch_size=[K, B])
        >>> out = loss(batch)
        >>> (out["loss_actor"] + out["loss_value"]).backward()
    """

    out_keys = ["loss_actor", "loss_value"]

    def __init__(self, actor_network: TensorDictModuleBase, value_network: EnsembleValueOperator, *,
                 gamma: float = 0.99, independent_batches: bool = False, member_actor_gradient: bool = False,
                 reward_bounds: tuple[float, float] | None = None, reward_key: str = "reward",
                 alpha_init: float = 0.01, fixed_alpha: bool = False, target_entropy="auto",
                 min_alpha: float | None = None, max_alpha: float | None = None, action_spec=None) -> None:
        super().__init__()
        if not isinstance(value_network, EnsembleValueOperator):
            raise TypeError(f"value_network must be an EnsembleValueOperator, got {type(value_network).__name__}.")
        gamma = float(gamma)
        if not 0.0 < gamma < 1.0:
            raise ValueError(f"gamma must lie in (0, 1), got {gamma!r}.")
        if reward_bounds is not None and not float(reward_bounds[0]) < float(reward_bounds[1]):
            raise ValueError(f"reward_bounds must be (low, high) with low < high, got {reward_bounds!r}.")
        self.gamma, self.reward_key = gamma, reward_key
        self.independent_batches, self.member_actor_gradient = bool(independent_batches), bool(member_actor_gradient)
        self.value_bounds = None if reward_bounds is None else tuple(float(b) / (1.0 - gamma) for b in reward_bounds)
        self.num_members = value_network.num_members
        self._observation_keys = list(value_network.in_keys[:-1])
        self.convert_to_functional(actor_network, "actor_network", create_target_params=True)
        self.convert_to_functional(value_network, "value_network", create_target_params=True)
        self._init_temperature(actor_network, alpha_init=alpha_init, fixed_alpha=fixed_alpha,
                               target_entropy=target_entropy, min_alpha=min_alpha, max_alpha=max_alpha,
                               action_spec=action_spec, entropy_sample="own")

    @property
    def draws_actor_rows(self) -> bool:
        """Whether :meth:`loss_actor` draws its rows itself (from a ``[K, B]`` batch): a caller passes it the
        critics' whole batch rather than rows drawn from it."""
        return self.independent_batches

    @property
    def in_keys(self) -> list:
        keys = [*self._observation_keys, "action"]
        return [*keys, *[("next", k) for k in self._observation_keys], ("next", self.reward_key),
                ("next", "terminated"), ("next", "done")]

    def _check(self, tensordict: TensorDictBase) -> None:
        k = self.num_members
        if self.independent_batches and (tensordict.batch_dims != 2 or tensordict.shape[0] != k):
            raise ValueError(f"with independent_batches the batch is [K, B] with K = {k} members, "
                             f"got batch shape {tuple(tensordict.shape)}.")
        if not self.independent_batches and tensordict.batch_dims != 1:
            raise ValueError(f"the batch is [B] (one batch shared by the members), got {tuple(tensordict.shape)}; "
                             "independent_batches=True takes [K, B].")

    def _act(self, tensordict: TensorDictBase, params) -> torch.Tensor:
        with params.to_module(self.actor_network):
            return self.actor_network(tensordict.select(*self.actor_network.in_keys)).get("action")

    def _values(self, tensordict: TensorDictBase, action: torch.Tensor, params) -> torch.Tensor:
        """``[K, B]``: member ``k`` on rows ``[k]`` of a ``[K, B]`` batch, or on all rows of a ``[B]`` batch."""
        net = self.value_network
        return net.members_logits(net.observation_from(tensordict), action.to(torch.float32), params)

    def targets(self, tensordict: TensorDictBase) -> torch.Tensor:
        """Each member's TD(0) target, ``[K, B]``, without gradient."""
        nxt = tensordict.get("next")
        with torch.no_grad():
            value = self._values(nxt, self._act(nxt, self.target_actor_network_params),
                                 self.target_value_network_params)
            reward, terminated = nxt.get(self.reward_key), nxt.get("terminated")
            if self.independent_batches:  # [K, B, 1 or K] -> [K, B]
                reward = reward[..., 0] if reward.shape[-1] == 1 else torch.diagonal(reward, dim1=0, dim2=-1).T
                terminated = terminated[..., 0]
            else:  # [B, 1 or K] -> [K, B]
                reward = reward.transpose(0, 1).expand(self.num_members, -1)
                terminated = terminated[..., 0].unsqueeze(0)
            target = reward + self.gamma * (~terminated.bool()).to(value.dtype) * value
            if self.value_bounds is not None:
                target = target.clamp(*self.value_bounds)
        return target

    def loss_value(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """The members' TD loss, ``mean (Q_k(s, a) - y_k)^2``, and its metadata."""
        self._check(tensordict)
        target = self.targets(tensordict)
        value = self._values(tensordict, tensordict.get("action"), self.value_network_params)
        return (value - target).pow(2).mean(), {"target_value": target.mean().detach(),
                                                "pred_value": value.mean().detach()}

    def loss_actor(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """``-mean Q(s, pi(s))``: the mean over the members, or with ``member_actor_gradient`` each row through
        one member (``B`` rows drawn with replacement from a ``[K, B]`` batch, each with its batch's member;
        on a ``[B]`` batch a member drawn per row). With a stochastic actor: on reparameterised samples, plus
        ``alpha * mean(log pi)`` (metadata ``log_prob``, ``entropy``, ``alpha``)."""
        if not self.stochastic:
            return self._value_actor_loss(tensordict), {}
        with set_exploration_type(ExplorationType.RANDOM):
            value_loss = self._value_actor_loss(tensordict)
            return self._entropy_terms(value_loss, None, lambda: self._act_td(tensordict, self.actor_network_params))

    def _act_td(self, tensordict: TensorDictBase, params) -> TensorDictBase:
        with params.to_module(self.actor_network):
            return self.actor_network(tensordict.select(*self.actor_network.in_keys))

    def _value_actor_loss(self, tensordict: TensorDictBase) -> torch.Tensor:
        self._check(tensordict)
        params = self.value_network_params.detach()
        if not self.member_actor_gradient:
            states = tensordict.reshape(-1)
            values = self._values(states, self._act(states, self.actor_network_params), params)  # [K, N]
            return -values.mean()
        if self.independent_batches:
            k, b = tensordict.shape
            flat = torch.randint(k * b, (b,), device=tensordict.device)
            members, states = flat // b, tensordict.reshape(-1)[flat]
        else:
            states = tensordict
            members = torch.randint(self.num_members, (states.shape[0],), device=tensordict.device)
        values = self._values(states, self._act(states, self.actor_network_params), params)  # [K, B]
        return -values.gather(0, members.unsqueeze(0)).mean()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        loss_value, meta = self.loss_value(tensordict)
        loss_actor, actor_meta = self.loss_actor(tensordict)
        out = TensorDict(meta, batch_size=[])
        out.set("loss_value", loss_value)
        out.set("loss_actor", loss_actor)
        if self.stochastic:
            out.set("loss_alpha", self.loss_alpha(actor_meta["log_prob"]))
            out.set("alpha", actor_meta["alpha"])
            out.set("entropy", actor_meta["entropy"])
        return out
