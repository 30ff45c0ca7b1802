"""The RCE loss, computed faster: the same losses as :class:`~torchrl_reset.RCELoss` with fewer passes."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase

from ..rce_loss import RCELoss, key_tuple, actor_loss, classifier_loss
from .ensemble import FastEnsembleValueOperator

__all__ = ["FastRCELoss"]


class FastRCELoss(RCELoss):
    """:class:`~torchrl_reset.RCELoss` with the classifier called on raw tensors in shared passes.

    The reference calls the classifier five times through its keys (target pass, examples, replay,
    actor) and the actor three times. Here, with a :class:`FastEnsembleValueOperator` classifier:

    - one actor pass serves ``s_{t+1}``, ``s_{t+n}`` and ``s*``; one target pass the first two;
    - the examples, the replay pairs and the actor's pairs share the members' state part
      (:meth:`FastEnsembleValueOperator.paired_logits`), and the priors' state part of each success
      example is kept between updates when the batch carries the examples' slots (``"index"``).

    The same losses up to float32 rounding (``tests/test_accel.py`` pins the two over several
    updates). With any other classifier it runs the reference :meth:`RCELoss.forward`.
    """

    def _fast(self) -> bool:
        return isinstance(self._networks[1], FastEnsembleValueOperator)

    def _label_and_weight(self, replay: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        if not self._fast():
            return super()._label_and_weight(replay)
        states = self._target_states(replay)
        return self._labels_from(self.classifier_network.observation_from(states), self._act(states), replay.shape[0])

    def _labels_from(self, observation: torch.Tensor, action: torch.Tensor, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Labels and weights from ``s_{t+1}`` (and ``s_{t+n}``) stacked, with the policy's actions there."""
        logits = self.classifier_network.logits(observation, action, self.target_classifier_network_params)
        return self._labels_of(torch.sigmoid(logits), batch)

    def _fast_terms(self, tensordict: TensorDictBase, with_actor: bool):
        """The classifier loss (and, with ``with_actor``, the actor loss on the same pass) with its label,
        weight and logits."""
        keys = self.tensor_keys
        replay, states, action, examples = self._read(tensordict)
        batch = replay.shape[0]
        slots = replay.get(key_tuple(keys.example_state) + key_tuple(keys.example_index), None)
        net = self.classifier_network

        with torch.no_grad(), self._label_mode():
            # One actor pass for s_{t+1}, s_{t+n} and s*; one target-classifier pass for the first two.
            targets = self._target_states(replay)
            num_targets = targets.shape[0]
            acting = torch.cat([targets, examples], 0)
            acting_obs = net.observation_from(acting)
            acting_actions = self._act(acting)
            label, weight = self._labels_from(acting_obs[:num_targets], acting_actions[:num_targets], batch)

        # Classifier loss on the examples and the replay rows; actor loss on (s_t, pi(s_t)). The
        # classifier's state part is computed once for both (FastEnsembleValueOperator.paired_logits).
        observation = torch.cat([acting_obs[num_targets:], net.observation_from(states)], 0)
        classifier_action = torch.cat([acting_actions[num_targets:], action.to(acting_actions.dtype)], 0)
        logits, actor_logits = net.paired_logits(
            observation, classifier_action, self._act(states) if with_actor else None, batch,
            self.classifier_network_params, slots=slots,
        )
        example_logits, replay_logits = logits[:batch], logits[batch:]
        loss_classifier = classifier_loss(example_logits, replay_logits, label, weight, self.gamma)
        loss_actor = None if actor_logits is None else actor_loss(actor_logits)
        return loss_classifier, loss_actor, label, weight, replay_logits, example_logits

    def loss_classifier(self, tensordict: TensorDictBase):
        if not self._fast():
            return super().loss_classifier(tensordict)
        loss, _, label, weight, replay_logits, example_logits = self._fast_terms(tensordict, with_actor=False)
        return loss, self._metadata(label, weight, replay_logits, example_logits)

    def _actor_value_loss(self, states: TensorDictBase, action: torch.Tensor) -> torch.Tensor:
        if not self._fast():
            return super()._actor_value_loss(states, action)
        net = self.classifier_network
        return actor_loss(net.logits(net.observation_from(states), action, self.classifier_network_params.detach()))

    def forward(self, tensordict: TensorDictBase):
        if not self._fast():
            return super().forward(tensordict)
        if self.stochastic:  # the actor's pass samples: it cannot share the classifier's deterministic pass
            loss, _, label, weight, replay_logits, example_logits = self._fast_terms(tensordict, with_actor=False)
            loss_actor, actor_meta = self._policy_loss(self._require(self._replay(tensordict), None, "s_t"))
            out = self._output(loss, loss_actor, label, weight, replay_logits, example_logits)
            return self._with_temperature(out, actor_meta)
        return self._output(*self._fast_terms(tensordict, with_actor=True))
