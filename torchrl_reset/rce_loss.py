"""Recursive classification of examples (RCE) for the reset agent (paper Eq. 2-3, docs/method.md section 3)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import LossModule

from ._validation import check_int
from .ensemble import EnsembleValueOperator, success_probability
from .stochastic_actor import StochasticActorMixin

#: the action the classifiers' labels (and the success examples' pairs) take: ``deterministic``, the actor's
#: noiseless action (a tanh-Gaussian's ``tanh(loc)`` onto the box); ``sample``, a draw of a stochastic actor
#: (RCE's original code)
LABEL_ACTIONS = ("deterministic", "sample")

__all__ = ["RCELoss", "LABEL_ACTIONS", "rce_label", "label_weight", "shared_label", "classifier_loss", "actor_loss"]


def key_tuple(key: NestedKey) -> tuple[str, ...]:
    return (key,) if isinstance(key, str) else tuple(key)


def _contains(keys, key: NestedKey) -> bool:
    return key_tuple(key) in {key_tuple(k) for k in keys}


def rce_label(c: torch.Tensor, discount: float) -> torch.Tensor:
    """Eq. 2's label ``discount * w / (1 + discount * w)`` with ``w = c / (1 - c)`` (Eq. 1), written with ``c``.

    ``discount = gamma`` for the next state, ``gamma ** n`` for the n-step state.
    """
    return discount * c / (1.0 + (discount - 1.0) * c)


def label_weight(label: torch.Tensor, gamma: float) -> torch.Tensor:
    """Eq. 2's replay weight ``1 + gamma * w``, with ``w`` the ratio of the label turned back into a
    classifier value ``c_y = y / (y + gamma (1 - y))`` clipped to [0, 0.5] (``w = w1`` when n = 1)."""
    c_y = (label / (label + gamma * (1.0 - label))).clamp(0.0, 0.5)
    return 1.0 + gamma * c_y / (1.0 - c_y)


def shared_label(next_value: torch.Tensor, gamma: float, nstep_value: torch.Tensor | None = None, n_steps: int = 1, *,
                 clip_values: bool = False, one_step: torch.Tensor | None = None) -> torch.Tensor:
    """The one label every member trains on (Eq. 2 with the release's n-step mix; docs/method.md sections 3, 9).

    ``next_value`` and ``nstep_value`` are the target classifiers' values ``C'_i`` at ``(s_{t+1}, pi(s_{t+1}))``
    and ``(s_{t+n}, pi(s_{t+n}))``, ``[..., B, K]`` (any leading dimensions, a run dimension included).
    Each member's label is :func:`rce_label` of the first, averaged with the n-step one when given; the
    minimum over the K members is the shared label, clipped at 0.5. ``clip_values`` clips the values to
    [0, 0.5] first (the other reading of section 9); ``one_step``, a boolean broadcastable to the values'
    leading dimensions (``[..., 1, 1]``), keeps the one-step label where it holds (a run whose batch fell
    back to n = 1). Returns ``[..., B]``.
    """
    if clip_values:
        next_value = next_value.clamp(0.0, 0.5)
        nstep_value = None if nstep_value is None else nstep_value.clamp(0.0, 0.5)
    label = rce_label(next_value, gamma)
    if nstep_value is not None:  # "Implementation details": y = (one-step label + n-step label) / 2
        both = 0.5 * (label + rce_label(nstep_value, gamma**n_steps))
        label = both if one_step is None else torch.where(one_step, label, both)
    return label.amin(-1).clamp(max=0.5)


def classifier_loss(example_logits: torch.Tensor, replay_logits: torch.Tensor, label: torch.Tensor,
                    weight: torch.Tensor, gamma: float) -> torch.Tensor:
    """Eq. 2 summed over members: ``(1 - gamma) mean_{s*} CE(C_i(s*, pi(s*)); 0.5) + mean_t w CE(C_i(s_t, a_t); y)``.

    Logits ``[..., B, K]`` (the success examples' and the replay rows'), the shared label and weight
    ``[..., B]``; the success label 1 is clipped to 0.5 like every label. Returns ``[...]``.
    """
    loss_examples = (1.0 - gamma) * F.binary_cross_entropy_with_logits(
        example_logits, torch.full_like(example_logits, 0.5), reduction="none"
    ).mean(-2)
    loss_replay = F.binary_cross_entropy_with_logits(
        replay_logits, label.unsqueeze(-1).expand_as(replay_logits), weight=weight.unsqueeze(-1), reduction="none"
    ).mean(-2)
    return (loss_examples + loss_replay).sum(-1)


def actor_loss(actor_logits: torch.Tensor) -> torch.Tensor:
    """The reset actor's loss, ``-mean_t min_i C_i(s_t, pi(s_t))`` (C itself, not the ratio), from the
    logits ``[..., B, K]`` of the policy's actions with the classifiers held fixed. Returns ``[...]``."""
    return -torch.sigmoid(actor_logits).amin(-1).mean(-1)


class RCELoss(StochasticActorMixin, LossModule):
    """The reset agent's loss: an RCE-trained classifier ensemble and its actor, deterministic (DDPG-style,
    the paper's) or stochastic (RCE's tanh-Gaussian, SAC's temperature: the project's reset actor).

    Paper: Kim et al. (RA-L 2022), Eq. 2-3 and "Implementation details", with the facts of the
    authors' implementation (docs/method.md section 3). For replay transitions ``(s_t, a_t, s_{t+1},
    s_{t+n})`` and success examples ``s*`` (examples of initial states), with target classifiers
    ``C'`` and actions from the current reset policy ``pi`` (no noise), and ``w(C) = C / (1 - C)``
    (in the weight, with ``C`` clipped to [0, 0.5]):

    - label, per member ``i``: ``y_i = 0.5 * (g C1 / (1 + (g - 1) C1) + g^n Cn / (1 + (g^n - 1) Cn))``
      with ``C1 = C'_i(s_{t+1}, pi(s_{t+1}))`` and ``Cn = C'_i(s_{t+n}, pi(s_{t+n}))``, the target
      values *unclipped* as in the authors' release (docs/method.md section 9); ``g C / (1 + (g - 1) C)``
      is ``g w / (1 + g w)`` written with ``C``, so with ``n = 1`` it is the one-step RCE label.
      ``clip_target_values=True`` clips ``C1`` and ``Cn`` to [0, 0.5] first (the other reading in
      docs/method.md section 9, which caps the n-step label at about 0.486);
    - the label shared by all members is the ensemble minimum ``y = min_i y_i``, clipped at 0.5;
    - weight ``1 + g w_y`` where ``w_y`` is the ratio of the label turned back into a classifier
      value, ``c_y = y / (y + g (1 - y))`` clipped to [0, 0.5] (``w_y = w1`` when ``n = 1``);
    - classifier loss, summed over members:
      ``(1 - g) mean_{s*} CE(C_i(s*, pi(s*)); 0.5) + mean_t (1 + g w_y) CE(C_i(s_t, a_t); y)``;
      the success label 1 is clipped to 0.5 like every label;
    - actor loss: ``-mean_t min_i C_i(s_t, pi(s_t))`` (the classifier value itself, not the ratio).

    This class is the plain reference path, written as the equations;
    :class:`torchrl_reset.accel.FastRCELoss` computes the same losses faster. Labels and weights carry no gradient; the actor loss reaches only the actor, the classifier
    loss only the trainable classifier parameters (never the priors). Target classifiers are
    updated by torchrl's :class:`~torchrl.objectives.SoftUpdate` (``tau=1e-3`` in the paper).

    Input (one tensordict, batch ``[B]``): the state entries and ``action`` at the root; the
    state at ``t+1`` under ``"next"``; the state at ``t+n`` under ``"nstep"`` (only when
    ``n_steps > 1``; :class:`~torchrl_reset.NStepStateTransform` writes it); a sample of ``B``
    success examples under ``"example"`` (:class:`~torchrl_reset.InitialStateBuffer`). The state
    entries are the actor's ``in_keys`` and the classifier's observation keys.

    Args:
        actor_network (TensorDictModule): the reset policy, writing the action key. Deterministic (a
            ``tanh`` head, :class:`~torchrl_reset.actor_heads.TanhHead`), or stochastic: a torchrl
            ``ProbabilisticActor`` (:class:`~torchrl_reset.actor_heads.TanhNormalHead`; any distribution with
            ``rsample`` and log-probabilities, written at ``action_log_prob``). With a stochastic actor the
            loss follows ``SACLoss``: the actor's loss scores reparameterised samples and adds
            ``alpha * mean(log pi(a|s))``, the output gains ``loss_alpha``, ``alpha`` and ``entropy``, and the
            temperature (``loss.temperature``) is a parameter of the loss.
        classifier_network (TensorDictModuleBase): the success-classifier ensemble, such as
            :class:`~torchrl_reset.EnsembleValueOperator`. The contract: it reads the state entries and
            the action key (its ``in_keys``) and writes the K members' logits, shaped ``[*batch, K]``,
            at the ``state_action_logit`` key (one of its ``out_keys``). The loss runs it on its own
            functional copies of the parameters (live, target and detached), swapped in with
            ``TensorDict.to_module`` as TorchRL losses do; any module keeping that contract works,
            for example K stock networks stacked with ``TensorDict.from_modules`` and run with
            ``torch.vmap`` (``docs/components.md`` shows one with priors).

    Keyword Args:
        gamma (float): discount in (0, 1). Defaults to 0.99. RCE's discount lives in the label,
            not in a value estimator, so it is an argument of the loss.
        n_steps (int): n of the n-step label. Defaults to 10.
        clip_target_values (bool): clip the target classifier values to [0, 0.5] before they become
            labels. Defaults to ``False`` (the release: only the label is clipped, at 0.5).
        label_action (str): the action ``pi(s)`` the labels take at ``s_{t+1}`` and ``s_{t+n}``, and the
            success examples' pairs at ``s*``: ``"deterministic"`` (default), the actor's noiseless action
            (for a tanh-Gaussian, ``tanh`` of the Gaussian's mean onto the box: what the project's runs use), or
            ``"sample"``, a draw of a stochastic actor (RCE's original code). Both are reasonable: the first
            gives the labels of the policy the trigger's state will be reset by, the second RCE's estimate of
            the expectation over the policy's actions.
        alpha_init (float): a stochastic actor's temperature, its first (or fixed) value. Defaults to 0.01.
        fixed_alpha (bool): keep alpha at ``alpha_init``. Defaults to False (learned, as SAC).
        target_entropy (float or "auto"): the learned alpha's target entropy; ``"auto"`` is ``-dim(A)`` (SAC's),
            read from ``action_spec`` or from the actor's own spec. Defaults to ``"auto"``.
        min_alpha, max_alpha (float, optional): bounds on alpha.
        action_spec (TensorSpec, optional): the action spec, for ``target_entropy="auto"``.
        entropy_sample (str): where the actor's ``log pi`` comes from: ``"own"`` (default), a second
            reparameterised sample at the same states (what the project's runs use); ``"shared"``, the very
            action the classifiers score (``SACLoss``'s).

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

        The project's reset actor, stochastic (RCE's tanh-Gaussian) with a learned temperature, SACLoss-style:

        >>> from torchrl.data import Bounded
        >>> from torchrl_reset.actor_heads import TanhNormalHead
        >>> head = TanhNormalHead()
        >>> stochastic = head.make_actor(obs_dim, Bounded(-1.0, 1.0, shape=(act_dim,)), (16, 16))
        >>> loss = RCELoss(stochastic, ensemble, n_steps=4, **head.loss_kwargs())
        >>> out = loss(batch)
        >>> sorted(k for k in out.keys() if k.startswith("loss")), round(float(out["alpha"]), 4)
        (['loss_actor', 'loss_alpha', 'loss_classifier'], 0.01)
        >>> (out["loss_classifier"] + out["loss_actor"] + out["loss_alpha"]).backward()
        >>> loss.temperature.log_alpha.grad is not None
        True

        Any classifier keeping the contract works, for instance one built from stock parts: K torchrl
        ``MLP`` members stacked with ``TensorDict.from_modules`` and run with ``torch.vmap``, each plus
        beta times a frozen prior (buffers, through ``TensorDictParams(..., no_convert=True)``):

        >>> from tensordict import TensorDictParams
        >>> from tensordict.nn import TensorDictModuleBase
        >>> from torchrl.modules import MLP
        >>> class StockEnsemble(TensorDictModuleBase):
        ...     in_keys, out_keys = ["observation", "action"], ["state_action_logit"]
        ...     def __init__(self, members, beta=3.0):
        ...         super().__init__()
        ...         make = lambda: MLP(in_features=obs_dim + act_dim, out_features=1, num_cells=[16, 16])
        ...         self.trained = TensorDict.from_modules(*[make() for _ in range(members)], as_module=True)
        ...         priors = TensorDict.from_modules(*[make() for _ in range(members)]).detach().clone()
        ...         self.priors = TensorDictParams(priors, no_convert=True)
        ...         self.__dict__["net"], self.beta = make().to("meta"), beta  # the layout, not a submodule
        ...     def forward(self, td):
        ...         x = torch.cat([td["observation"], td["action"]], -1)
        ...         def member(f, g):
        ...             with f.to_module(self.net):
        ...                 out = self.net(x)
        ...             with g.to_module(self.net):
        ...                 prior = self.net(x)
        ...             return out + self.beta * prior
        ...         logits = torch.vmap(member)(self.trained, self.priors)  # [K, B, 1]
        ...         return td.set("state_action_logit", logits.squeeze(-1).movedim(0, -1))  # [B, K]
        >>> loss = RCELoss(actor, StockEnsemble(4), n_steps=4)
        >>> updater = SoftUpdate(loss, tau=1e-3)
        >>> out = loss(batch)
        >>> (out["loss_actor"] + out["loss_classifier"]).backward()
        >>> updater.step()
    """

    @dataclass
    class _AcceptedKeys:
        """The tensordict keys this loss reads and writes; rename them with :meth:`set_keys`.

        Attributes:
            action (NestedKey): the action taken (replay) and written by the actor. Defaults to ``"action"``.
            state_action_logit (NestedKey): the classifier's per-member logits, ``[*batch, K]``; must be one
                of the classifier's ``out_keys``. Defaults to the classifier's out_key when it has
                exactly one, else ``"state_action_logit"``.
            next_state (NestedKey): the sub-tensordict holding ``s_{t+1}``. Defaults to ``"next"``.
            nstep_state (NestedKey): the sub-tensordict holding ``s_{t+n}``. Defaults to ``"nstep"``.
            example_state (NestedKey): the sub-tensordict holding the success examples. Defaults to ``"example"``.
            example_index (NestedKey): inside ``example_state``, each example's slot in its buffer
                (:meth:`InitialStateBuffer.sample <torchrl_reset.InitialStateBuffer.sample>` writes
                it). Optional, read only by :class:`~torchrl_reset.accel.FastRCELoss`, which then
                computes the priors' part of each example once and keeps it. Defaults to ``"index"``.
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
        log_prob: NestedKey = "action_log_prob"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_classifier", "loss_actor"]  # and loss_alpha with a stochastic actor

    actor_network: TensorDictModule
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    classifier_network: TensorDictModuleBase
    classifier_network_params: TensorDictParams
    target_classifier_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: TensorDictModuleBase,
        classifier_network: TensorDictModuleBase,
        *,
        gamma: float = 0.99,
        n_steps: int = 10,
        clip_target_values: bool = False,
        label_action: str = "deterministic",
        alpha_init: float = 0.01,
        fixed_alpha: bool = False,
        target_entropy: float | str = "auto",
        min_alpha: float | None = None,
        max_alpha: float | None = None,
        action_spec=None,
        entropy_sample: str = "own",
    ) -> None:
        super().__init__()
        if label_action not in LABEL_ACTIONS:
            raise ValueError(f"label_action must be one of {LABEL_ACTIONS}, got {label_action!r}.")
        gamma = float(gamma)
        if not (0.0 < gamma < 1.0):
            raise ValueError(f"gamma must lie in (0, 1), got {gamma!r}.")
        check_int("n_steps", n_steps)
        for name, net in (("actor_network", actor_network), ("classifier_network", classifier_network)):
            if not isinstance(net, TensorDictModuleBase):
                raise TypeError(
                    f"{name} must be a tensordict module (with in_keys and out_keys), got {type(net).__name__}."
                )
        self._tensor_keys = self._AcceptedKeys()
        if len(classifier_network.out_keys) == 1:
            self._tensor_keys.state_action_logit = classifier_network.out_keys[0]
        self.gamma = gamma
        self.n_steps = n_steps
        self.clip_target_values = bool(clip_target_values)
        self._networks = (actor_network, classifier_network)
        self._check_keys()
        self.convert_to_functional(actor_network, "actor_network")
        self.convert_to_functional(classifier_network, "classifier_network", create_target_params=True)
        self._share_priors_with_target()
        self.label_action = label_action
        self._init_temperature(actor_network, alpha_init=alpha_init, fixed_alpha=fixed_alpha,
                               target_entropy=target_entropy, min_alpha=min_alpha, max_alpha=max_alpha,
                               action_spec=action_spec, entropy_sample=entropy_sample)
        self.log_prob_key = self.tensor_keys.log_prob

    def _label_mode(self):
        """The exploration mode of the labels' and the examples' actions (``label_action``)."""
        return set_exploration_type(ExplorationType.RANDOM if self.label_action == "sample"
                                    else ExplorationType.DETERMINISTIC)

    def _check_keys(self) -> None:
        """The keys agree with the networks: checked at construction and after every :meth:`set_keys`."""
        actor, classifier = self._networks
        keys = self.tensor_keys
        if not _contains(actor.out_keys, keys.action):
            raise ValueError(f"the actor must write the action key {keys.action!r}; its out_keys are {actor.out_keys}.")
        if not _contains(classifier.in_keys, keys.action):
            raise ValueError(f"the classifier must read the action key {keys.action!r}; its in_keys are {classifier.in_keys}.")
        if not _contains(classifier.out_keys, keys.state_action_logit):
            raise ValueError(
                f"state_action_logit is {keys.state_action_logit!r}, but the classifier writes {classifier.out_keys}; "
                "name one of those (set_keys(state_action_logit=...))."
            )
        state_keys = []
        for key in [*actor.in_keys, *classifier.in_keys]:
            if not _contains([keys.action], key) and not _contains(state_keys, key):
                state_keys.append(key)
        self._state_keys = state_keys
        self._actor_in_keys = list(actor.in_keys)

    def _share_priors_with_target(self) -> None:
        # EnsembleValueOperator's priors are buffers: the target copy made by convert_to_functional
        # would be a clone. Point it at the same tensors so that "the target uses the same prior g_i"
        # holds by construction.
        if not (isinstance(self._networks[1], EnsembleValueOperator) and self._networks[1].has_prior):
            return
        source = self.classifier_network_params
        # read the module directly: the attribute access would warn that no target updater exists yet
        target = self._modules["target_classifier_network_params"]
        was_locked = target.is_locked
        if was_locked:
            target.unlock_()
        for key in list(source.keys(True, True)):
            name = key if isinstance(key, str) else key[-1]
            if name.startswith("prior_"):
                target.set(key, source.get(key))
        if was_locked:
            target.lock_()

    def set_keys(self, **kwargs) -> None:
        """Renames tensordict keys (torchrl's :meth:`~torchrl.objectives.LossModule.set_keys`); keys that
        disagree with the networks raise ``ValueError`` and leave the loss's keys as they were."""
        before = replace(self._tensor_keys)
        try:
            super().set_keys(**kwargs)
        except ValueError:
            self._tensor_keys = before
            raise

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        # RCE has no value estimator (its bootstrapped label is computed in forward); set_keys lands
        # here after renaming, so the new keys are checked against the networks.
        if hasattr(self, "_networks"):
            self._check_keys()

    def make_value_estimator(self, *args, **kwargs):
        raise NotImplementedError("RCELoss computes its own label (docs/method.md section 3); it takes no value estimator.")

    @property
    def state_keys(self) -> list[NestedKey]:
        """The state entries read at the root and in the next, n-step and example sub-tensordicts."""
        return list(self._state_keys)

    @property
    def in_keys(self) -> list[NestedKey]:
        """Every entry the loss reads, as torchrl's losses list theirs (``DDPGLoss.in_keys``): the state keys
        at the root and under the next, n-step and example sub-tensordicts, the action and the optional
        ``one_step`` flag. A replay buffer keeps the ones a collected step has (``select(*in_keys,
        strict=False)``); the n-step states and the examples are added when a batch is sampled."""
        keys = self.tensor_keys
        subs = (keys.next_state, keys.nstep_state, keys.example_state)
        return [*self._state_keys, keys.action,
                *[(*key_tuple(sub), *key_tuple(key)) for sub in subs for key in self._state_keys], keys.one_step]

    # -- reading the batch ------------------------------------------------------------------------

    def _require(self, tensordict: TensorDictBase, sub: NestedKey | None, what: str) -> TensorDictBase:
        data = tensordict if sub is None else tensordict.get(sub, None)
        if data is None:
            raise KeyError(
                f"RCELoss needs the entry {sub!r} ({what}) in its input; got {sorted(map(str, tensordict.keys()))}."
            )
        present = {key_tuple(k) for k in data.keys(True, True)}
        missing = [key for key in self._state_keys if key_tuple(key) not in present]
        if missing:
            where = "the root" if sub is None else repr(sub)
            raise KeyError(f"RCELoss needs the state key(s) {missing} under {where} ({what}).")
        return data.select(*self._state_keys)

    def _replay(self, tensordict: TensorDictBase) -> TensorDictBase:
        replay = tensordict.reshape(-1) if tensordict.batch_dims != 1 else tensordict
        if replay.shape[0] == 0:
            raise ValueError("RCELoss got an empty batch.")
        return replay

    def _uses_nstep(self, replay: TensorDictBase) -> bool:
        if self.n_steps == 1:
            return False
        one_step = replay.get(self.tensor_keys.one_step, None)
        return one_step is None or not bool(one_step.all())

    def _target_states(self, replay: TensorDictBase) -> TensorDictBase:
        """``s_{t+1}`` (and ``s_{t+n}`` when n > 1) stacked, for one actor and one target pass."""
        states = [self._require(replay, self.tensor_keys.next_state, "s_{t+1}")]
        if self._uses_nstep(replay):
            states.append(self._require(replay, self.tensor_keys.nstep_state, "s_{t+n}"))
        return torch.cat(states, 0)

    # -- the networks through their keys ----------------------------------------------------------

    def _act(self, states: TensorDictBase) -> torch.Tensor:
        """``pi(s)``: the reset policy on its live parameters (in the exploration mode in force)."""
        return self._act_td(states).get(self.tensor_keys.action)

    def _act_td(self, states: TensorDictBase) -> TensorDictBase:
        """The reset policy's output at ``states`` (action, and a stochastic actor's ``log_prob``)."""
        with self.actor_network_params.to_module(self.actor_network):
            return self.actor_network(states.select(*self._actor_in_keys))

    def _classify(self, states: TensorDictBase, action: torch.Tensor, params: TensorDictBase) -> torch.Tensor:
        """The members' logits ``[B, K]`` of ``(states, action)`` with the classifier's parameters ``params``."""
        pairs = states.clone(False).set(self.tensor_keys.action, action)
        with params.to_module(self.classifier_network):
            logits = self.classifier_network(pairs).get(self.tensor_keys.state_action_logit)
        if logits.dim() != 2 or logits.shape[0] != states.shape[0]:
            raise ValueError(
                f"the classifier must write its members' logits as [batch, K] at {self.tensor_keys.state_action_logit!r}; "
                f"got shape {tuple(logits.shape)} for a batch of {states.shape[0]}."
            )
        return logits

    # -- the loss -----------------------------------------------------------------------------------

    def labels(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """The shared label ``y`` and weight ``1 + gamma * w_y`` for each transition, without gradient."""
        replay = self._replay(tensordict)
        with torch.no_grad(), self._label_mode():
            return self._label_and_weight(replay)

    def _label_and_weight(self, replay: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        batch = replay.shape[0]
        targets = self._target_states(replay)  # s_{t+1} rows, then s_{t+n} rows
        # Eq. 1: C'_i at the next states with the policy's actions, from the target classifiers
        value = torch.sigmoid(self._classify(targets, self._act(targets), self.target_classifier_network_params))
        return self._labels_of(value, batch)

    def _labels_of(self, value: torch.Tensor, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The shared label and weight from the target values at ``s_{t+1}`` (rows ``:batch``) and ``s_{t+n}``."""
        nstep = value[batch:] if value.shape[0] > batch else None
        label = shared_label(value[:batch], self.gamma, nstep, self.n_steps, clip_values=self.clip_target_values)
        return label, label_weight(label, self.gamma)

    def _read(self, tensordict: TensorDictBase):
        """The batch's replay rows, ``s_t``, ``a_t`` and success examples, checked."""
        replay = self._replay(tensordict)
        states = self._require(replay, None, "s_t")
        action = replay.get(self.tensor_keys.action, None)
        if action is None:
            raise KeyError(f"RCELoss needs the action key {self.tensor_keys.action!r} at the root of its input.")
        examples = self._require(replay, self.tensor_keys.example_state, "success examples s*")
        if examples.shape[0] != replay.shape[0]:
            raise ValueError(
                f"RCELoss needs one success example per replay row: got {examples.shape[0]} for {replay.shape[0]}."
            )
        return replay, states, action, examples

    def _classifier_terms(self, replay, states, action, examples):
        """Eq. 2 on the batch: the classifier loss summed over members, with its label, weight and logits."""
        with torch.no_grad(), self._label_mode():
            label, weight = self._label_and_weight(replay)
            example_action = self._act(examples)  # a ~ pi(s*) in Eq. 2's first term

        # Eq. 2, per member i, summed over members: (1 - gamma) CE(C_i(s*, pi(s*)); 1) with the success
        # label clipped to 0.5 like every label, plus (1 + gamma w) CE(C_i(s_t, a_t); y)
        example_logits = self._classify(examples, example_action, self.classifier_network_params)
        replay_logits = self._classify(states, action.to(example_action.dtype), self.classifier_network_params)
        return self._classifier_loss(example_logits, replay_logits, label, weight), label, weight, replay_logits, example_logits

    def _classifier_loss(self, example_logits, replay_logits, label, weight) -> torch.Tensor:
        return classifier_loss(example_logits, replay_logits, label, weight, self.gamma)

    def _actor_loss(self, states: TensorDictBase) -> torch.Tensor:
        """The actor: gradient ascent on the ensemble minimum of C_i(s, pi(s)), the classifier held fixed."""
        return self._actor_value_loss(states, self._act(states))

    def _actor_value_loss(self, states: TensorDictBase, action: torch.Tensor) -> torch.Tensor:
        """``-mean_t min_i C_i(s_t, a_t)`` for the policy's actions ``action``, the classifiers held fixed."""
        return actor_loss(self._classify(states, action, self.classifier_network_params.detach()))

    def _policy_loss(self, states: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """The actor's loss at ``states``: deterministic, :meth:`_actor_loss`; stochastic, on a reparameterised
        sample, plus ``alpha * mean(log pi)`` (its metadata: ``log_prob``, ``entropy``, ``alpha``)."""
        if not self.stochastic:
            return self._actor_loss(states), {}
        with set_exploration_type(ExplorationType.RANDOM):
            acted = self._act_td(states)
            value_loss = self._actor_value_loss(states, acted.get(self.tensor_keys.action))
            return self._entropy_terms(value_loss, acted, lambda: self._act_td(states))

    def loss_classifier(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """The classifier loss alone (Eq. 2; gradient to the trainable classifier parameters only) and its
        metadata (``label``, ``weight``, ``success_probability``, ``example_classifier``), as torchrl's
        ``DDPGLoss.loss_value``: for an update of the classifiers before the actor (the release's order)."""
        loss, label, weight, replay_logits, example_logits = self._classifier_terms(*self._read(tensordict))
        return loss, self._metadata(label, weight, replay_logits, example_logits)

    def loss_actor(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """The actor loss alone, ``-mean_t min_i C_i(s_t, pi(s_t))`` with the classifiers as they are now
        (gradient to the actor only), as torchrl's ``DDPGLoss.loss_actor``. Reads only the replay states. With a
        stochastic actor, ``pi(s_t)`` is a reparameterised sample and the loss adds ``alpha * mean(log pi)``;
        the metadata then holds ``log_prob`` (detached, for :meth:`loss_alpha`), ``entropy`` and ``alpha``."""
        replay = self._replay(tensordict)
        return self._policy_loss(self._require(replay, None, "s_t"))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Both losses on one batch with the classifiers as they are before the update (the loss of a joint
        step); :meth:`loss_classifier` and :meth:`loss_actor` give them one at a time."""
        replay, states, action, examples = self._read(tensordict)
        loss_classifier, label, weight, replay_logits, example_logits = self._classifier_terms(replay, states, action, examples)
        loss_actor, actor_meta = self._policy_loss(states)
        out = self._output(loss_classifier, loss_actor, label, weight, replay_logits, example_logits)
        return self._with_temperature(out, actor_meta)

    def _with_temperature(self, out: TensorDict, actor_meta: dict) -> TensorDict:
        """A stochastic actor's entries beside the losses: ``loss_alpha`` (with its graph), ``alpha``, ``entropy``."""
        if self.stochastic:
            out.set("loss_alpha", self.loss_alpha(actor_meta["log_prob"]))
            out.set("alpha", actor_meta["alpha"])
            out.set("entropy", actor_meta["entropy"])
        return out

    @staticmethod
    def _metadata(label, weight, replay_logits, example_logits) -> dict:
        with torch.no_grad():
            return {
                "label": label.mean(),
                "weight": weight.mean(),
                "success_probability": success_probability(replay_logits).mean(),
                "example_classifier": torch.sigmoid(example_logits).mean(),
            }

    @classmethod
    def _output(cls, loss_classifier, loss_actor, label, weight, replay_logits, example_logits) -> TensorDict:
        out = TensorDict(cls._metadata(label, weight, replay_logits, example_logits), batch_size=[])
        # the loss entries keep their graph
        out.set("loss_classifier", loss_classifier)
        out.set("loss_actor", loss_actor)
        return out

    def extra_repr(self) -> str:
        text = f"gamma={self.gamma}, n_steps={self.n_steps}, clip_target_values={self.clip_target_values}"
        if self.stochastic:
            text += f", label_action={self.label_action!r}, entropy_sample={self.entropy_sample!r}"
        return text

