"""Recursive classification of examples (RCE) for the reset agent (method.md section 3)."""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.envs.utils import set_exploration_type
from torchrl.objectives import LossModule

from ._validation import check_int
from .ensemble import EnsembleValueOperator, success_probability

__all__ = ["RCELoss"]


def _as_tuple(key: NestedKey) -> tuple[str, ...]:
    return (key,) if isinstance(key, str) else tuple(key)


class RCELoss(LossModule):
    """The reset agent's loss: an RCE-trained classifier ensemble and a DDPG-style actor.

    Paper: Kim et al. (RA-L 2022), Eq. 2-3 and "Implementation details", with the facts of the
    authors' implementation (method.md section 3). For replay transitions ``(s_t, a_t, s_{t+1},
    s_{t+n})`` and success examples ``s*`` (examples of initial states), with target classifiers
    ``C'`` and actions from the current reset policy ``pi`` (no noise), and ``w(C) = C / (1 - C)``
    (in the weight, with ``C`` clipped to [0, 0.5]):

    - label, per member ``i``: ``y_i = 0.5 * (g C1 / (1 + (g - 1) C1) + g^n Cn / (1 + (g^n - 1) Cn))``
      with ``C1 = C'_i(s_{t+1}, pi(s_{t+1}))`` and ``Cn = C'_i(s_{t+n}, pi(s_{t+n}))``, the target
      values *unclipped* as in the authors' release (method.md section 9); ``g C / (1 + (g - 1) C)``
      is ``g w / (1 + g w)`` written with ``C``, so with ``n = 1`` it is the one-step RCE label.
      ``clip_target_values=True`` clips ``C1`` and ``Cn`` to [0, 0.5] first (method.md section 3's
      reading, which caps the n-step label at about 0.486);
    - the label shared by all members is the ensemble minimum ``y = min_i y_i``, clipped at 0.5;
    - weight ``1 + g w_y`` where ``w_y`` is the ratio of the label turned back into a classifier
      value, ``c_y = y / (y + g (1 - y))`` clipped to [0, 0.5] (``w_y = w1`` when ``n = 1``);
    - classifier loss, summed over members:
      ``(1 - g) mean_{s*} CE(C_i(s*, pi(s*)); 0.5) + mean_t (1 + g w_y) CE(C_i(s_t, a_t); y)``;
      the success label 1 is clipped to 0.5 like every label;
    - actor loss: ``-mean_t min_i C_i(s_t, pi(s_t))`` (the classifier value itself, not the ratio).

    Labels and weights carry no gradient; the actor loss reaches only the actor, the classifier
    loss only the trainable classifier parameters (never the priors). Target classifiers are
    updated by torchrl's :class:`~torchrl.objectives.SoftUpdate` (``tau=1e-3`` in the paper).

    Input (one tensordict, batch ``[B]``): the state entries and ``action`` at the root; the
    state at ``t+1`` under ``"next"``; the state at ``t+n`` under ``"nstep"`` (only when
    ``n_steps > 1``; :class:`~torchrl_reset.NStepStateTransform` writes it); a sample of ``B``
    success examples under ``"example"`` (:class:`~torchrl_reset.InitialStateBuffer`). The state
    entries are the actor's ``in_keys`` and the classifier's observation keys.

    Args:
        actor_network (TensorDictModule): the reset policy, writing the action key (deterministic:
            the loss always runs in deterministic exploration mode).
        classifier_network (EnsembleValueOperator): the success-classifier ensemble.

    Keyword Args:
        gamma (float): discount in (0, 1). Defaults to 0.99. RCE's discount lives in the label,
            not in a value estimator, so it is an argument of the loss.
        n_steps (int): n of the n-step label. Defaults to 10.
        clip_target_values (bool): clip the target classifier values to [0, 0.5] before they become
            labels. Defaults to ``False`` (the release: only the label is clipped, at 0.5).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torch import nn
        >>> from torchrl.objectives import SoftUpdate
        >>> from torchrl_reset import EnsembleValueOperator, RCELoss
        >>> obs_dim, act_dim, B = 3, 2, 8
        >>> actor = TensorDictModule(nn.Sequential(nn.Linear(obs_dim, act_dim), nn.Tanh()),
        ...                          in_keys=["observation"], out_keys=["action"])
        >>> ensemble = EnsembleValueOperator(obs_dim, act_dim, num_members=3, hidden_sizes=(16, 16))
        >>> loss = RCELoss(actor, ensemble, n_steps=4)
        >>> updater = SoftUpdate(loss, tau=1e-3)
        >>> state = lambda: TensorDict(observation=torch.randn(B, obs_dim), batch_size=[B])
        >>> batch = TensorDict(observation=torch.randn(B, obs_dim), action=torch.rand(B, act_dim) * 2 - 1,
        ...                    next=state(), nstep=state(), example=state(), batch_size=[B])
        >>> out = loss(batch)
        >>> sorted(k for k in out.keys() if k.startswith("loss"))
        ['loss_actor', 'loss_classifier']
        >>> (out["loss_actor"] + out["loss_classifier"]).backward()
        >>> updater.step()
    """

    @dataclass
    class _AcceptedKeys:
        """The tensordict keys this loss reads and writes; rename them with :meth:`set_keys`.

        Attributes:
            action (NestedKey): the action taken (replay) and written by the actor. Defaults to ``"action"``.
            state_action_logit (NestedKey): the classifier's per-member logits. Defaults to ``"state_action_logit"``.
            next_state (NestedKey): the sub-tensordict holding ``s_{t+1}``. Defaults to ``"next"``.
            nstep_state (NestedKey): the sub-tensordict holding ``s_{t+n}``. Defaults to ``"nstep"``.
            example_state (NestedKey): the sub-tensordict holding the success examples. Defaults to ``"example"``.
            example_index (NestedKey): inside ``example_state``, each example's slot in its buffer
                (:meth:`InitialStateBuffer.sample <torchrl_reset.InitialStateBuffer.sample>` writes
                it). Optional: when present, the priors' part of each example is computed once and
                kept (:meth:`EnsembleValueOperator.paired_logits`). Defaults to ``"index"``.
            one_step (NestedKey): optional boolean entry at the root; when it holds True the batch gets
                the one-step label and needs no ``"nstep"`` entry (the release's fallback while no
                reset episode has n transitions: :class:`~torchrl_reset.EpisodeWindowSampler`).
                Defaults to ``"one_step"``.
        """

        action: NestedKey = "action"
        state_action_logit: NestedKey = "state_action_logit"
        next_state: NestedKey = "next"
        nstep_state: NestedKey = "nstep"
        example_state: NestedKey = "example"
        example_index: NestedKey = "index"
        one_step: NestedKey = "one_step"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_classifier", "loss_actor"]

    actor_network: TensorDictModule
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    classifier_network: EnsembleValueOperator
    classifier_network_params: TensorDictParams
    target_classifier_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: TensorDictModule,
        classifier_network: EnsembleValueOperator,
        *,
        gamma: float = 0.99,
        n_steps: int = 10,
        clip_target_values: bool = False,
    ) -> None:
        super().__init__()
        gamma = float(gamma)
        if not (0.0 < gamma < 1.0):
            raise ValueError(f"gamma must lie in (0, 1), got {gamma!r}.")
        check_int("n_steps", n_steps)
        if not isinstance(classifier_network, EnsembleValueOperator):
            raise TypeError(
                f"classifier_network must be an EnsembleValueOperator, got {type(classifier_network).__name__}."
            )
        self._tensor_keys = self._AcceptedKeys()
        self.gamma = gamma
        self.n_steps = n_steps
        self.clip_target_values = bool(clip_target_values)
        self._check_networks(actor_network, classifier_network)
        self.convert_to_functional(actor_network, "actor_network")
        self.convert_to_functional(classifier_network, "classifier_network", create_target_params=True)
        self._share_priors_with_target()

    def _check_networks(self, actor, classifier) -> None:
        action = self.tensor_keys.action
        if _as_tuple(classifier.in_keys[-1]) != _as_tuple(action):
            raise ValueError(
                f"the classifier's last in_key must be the action key {action!r}, got {classifier.in_keys[-1]!r}."
            )
        if _as_tuple(action) not in {_as_tuple(k) for k in actor.out_keys}:
            raise ValueError(f"the actor must write the action key {action!r}; its out_keys are {actor.out_keys}.")
        if _as_tuple(classifier.out_keys[0]) != _as_tuple(self.tensor_keys.state_action_logit):
            self.tensor_keys.state_action_logit = classifier.out_keys[0]
        keys = []
        for key in [*actor.in_keys, *classifier.in_keys[:-1]]:
            if _as_tuple(key) not in {_as_tuple(k) for k in keys}:
                keys.append(key)
        self._state_keys = keys
        self._actor_in_keys = list(actor.in_keys)
        self._classifier_state_keys = list(classifier.in_keys[:-1])

    def _share_priors_with_target(self) -> None:
        # The priors are buffers: the target copy made by convert_to_functional would be a clone.
        # Point it at the same tensors so that "the target uses the same prior g_i" holds by construction.
        if not self.classifier_network.has_prior:
            return
        source = self.classifier_network_params
        # read the module directly: the attribute access would warn that no target updater exists yet
        target = self._modules["target_classifier_network_params"]
        unlocked = target.is_locked
        if unlocked:
            target.unlock_()
        for key in list(source.keys(True, True)):
            name = key if isinstance(key, str) else key[-1]
            if name.startswith("prior_"):
                target.set(key, source.get(key))
        if unlocked:
            target.lock_()

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        # RCE has no value estimator: its bootstrapped label is computed in forward.
        pass

    def make_value_estimator(self, *args, **kwargs):
        raise NotImplementedError("RCELoss computes its own label (method.md section 3); it takes no value estimator.")

    @property
    def state_keys(self) -> list[NestedKey]:
        """The state entries read at the root and in the next, n-step and example sub-tensordicts."""
        return list(self._state_keys)

    def _require(self, tensordict: TensorDictBase, sub: NestedKey | None, what: str) -> TensorDictBase:
        data = tensordict if sub is None else tensordict.get(sub, None)
        if data is None:
            raise KeyError(
                f"RCELoss needs the entry {sub!r} ({what}) in its input; got {sorted(map(str, tensordict.keys()))}."
            )
        present = {_as_tuple(k) for k in data.keys(True, True)}
        missing = [key for key in self._state_keys if _as_tuple(key) not in present]
        if missing:
            where = "the root" if sub is None else repr(sub)
            raise KeyError(f"RCELoss needs the state key(s) {missing} under {where} ({what}).")
        return data.select(*self._state_keys)

    def _act(self, data: TensorDictBase) -> torch.Tensor:
        with self.actor_network_params.to_module(self.actor_network):
            return self.actor_network(data.select(*self._actor_in_keys)).get(self.tensor_keys.action)

    def labels(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """The shared label ``y`` and weight ``1 + gamma * w_y`` for each transition, without gradient."""
        replay = tensordict.reshape(-1) if tensordict.batch_dims != 1 else tensordict
        # the actions of the current policy without noise, as in forward (which torchrl runs deterministically)
        with torch.no_grad(), set_exploration_type(self.deterministic_sampling_mode):
            states = self._target_states(replay)
            return self._labels_from(self.classifier_network.observation_from(states), self._act(states), replay.shape[0])

    def _target_states(self, replay: TensorDictBase) -> TensorDictBase:
        """``s_{t+1}`` (and ``s_{t+n}`` when n > 1) stacked, for one actor and one target pass."""
        states = [self._require(replay, self.tensor_keys.next_state, "s_{t+1}")]
        if self._uses_nstep(replay):
            states.append(self._require(replay, self.tensor_keys.nstep_state, "s_{t+n}"))
        return torch.cat(states, 0)

    def _uses_nstep(self, replay: TensorDictBase) -> bool:
        if self.n_steps == 1:
            return False
        one_step = replay.get(self.tensor_keys.one_step, None)
        return one_step is None or not bool(one_step.all())

    def _labels_from(self, observation: torch.Tensor, action: torch.Tensor, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Labels and weights from ``s_{t+1}`` (and ``s_{t+n}``) stacked, with the policy's actions there."""
        gamma = self.gamma
        logits = self.classifier_network.logits(observation, action, self.target_classifier_network_params)
        value = torch.sigmoid(logits)
        if self.clip_target_values:
            value = value.clamp(0.0, 0.5)

        def label_of(c: torch.Tensor, discount: float) -> torch.Tensor:
            return discount * c / (1.0 + (discount - 1.0) * c)  # = discount w / (1 + discount w), w = c / (1 - c)

        label = label_of(value[:batch], gamma)
        if value.shape[0] > batch:  # the n-step part
            label = 0.5 * (label + label_of(value[batch:], gamma**self.n_steps))
        label = label.amin(-1).clamp(max=0.5)
        classifier_value = (label / (label + gamma * (1.0 - label))).clamp(0.0, 0.5)
        weight = 1.0 + gamma * classifier_value / (1.0 - classifier_value)
        return label, weight

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        replay = tensordict.reshape(-1) if tensordict.batch_dims != 1 else tensordict
        batch = replay.shape[0]
        if batch == 0:
            raise ValueError("RCELoss got an empty batch.")
        states = self._require(replay, None, "s_t")
        action = replay.get(keys.action, None)
        if action is None:
            raise KeyError(f"RCELoss needs the action key {keys.action!r} at the root of its input.")
        examples = self._require(replay, keys.example_state, "success examples s*")
        slots = replay.get(_as_tuple(keys.example_state) + _as_tuple(keys.example_index), None)
        if examples.shape[0] != batch:
            raise ValueError(f"RCELoss needs one success example per replay row: got {examples.shape[0]} for {batch}.")
        gamma = self.gamma
        net = self.classifier_network

        with torch.no_grad():
            # One actor pass for s_{t+1}, s_{t+n} and s*; one target-classifier pass for the first two.
            targets = self._target_states(replay)
            num_targets = targets.shape[0]
            acting = torch.cat([targets, examples], 0)
            acting_obs = net.observation_from(acting)
            acting_actions = self._act(acting)
            label, weight = self._labels_from(acting_obs[:num_targets], acting_actions[:num_targets], batch)

        # Classifier loss on the examples and the replay rows; actor loss on (s_t, pi(s_t)). The
        # classifier's state part is computed once for both (EnsembleValueOperator.paired_logits).
        observation = torch.cat([acting_obs[num_targets:], net.observation_from(states)], 0)
        classifier_action = torch.cat([acting_actions[num_targets:], action.to(acting_actions.dtype)], 0)
        logits, actor_logits = net.paired_logits(
            observation, classifier_action, self._act(states), batch, self.classifier_network_params, slots=slots
        )
        example_logits, replay_logits = logits[:batch], logits[batch:]
        loss_examples = (1.0 - gamma) * F.binary_cross_entropy_with_logits(
            example_logits, torch.full_like(example_logits, 0.5), reduction="none"
        ).mean(0)
        loss_replay = F.binary_cross_entropy_with_logits(
            replay_logits,
            label.unsqueeze(-1).expand_as(replay_logits),
            weight=weight.unsqueeze(-1),
            reduction="none",
        ).mean(0)
        loss_classifier = (loss_examples + loss_replay).sum()
        # Actor loss: maximise the ensemble minimum of C(s, pi(s)); classifier parameters held out.
        loss_actor = -torch.sigmoid(actor_logits).amin(-1).mean()

        with torch.no_grad():
            out = TensorDict(
                {
                    "loss_classifier": loss_classifier,
                    "loss_actor": loss_actor,
                    "label": label.mean(),
                    "weight": weight.mean(),
                    "success_probability": success_probability(replay_logits).mean(),
                    "example_classifier": torch.sigmoid(example_logits).mean(),
                },
                batch_size=[],
            )
        # the loss entries must keep their graph
        out.set("loss_classifier", loss_classifier)
        out.set("loss_actor", loss_actor)
        return out

    def extra_repr(self) -> str:
        return f"gamma={self.gamma}, n_steps={self.n_steps}, clip_target_values={self.clip_target_values}, num_members={self.classifier_network.num_members}"

