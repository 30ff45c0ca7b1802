"""S runs' agents updated by one call: the DDPG and RCE updates batched along a run dimension.

Each run keeps its own modules (its policy, its critic or classifier ensemble, its loss module with
its target copies), built exactly as for a run alone, so that acting, the trigger, evaluation and
checkpoints work on each run as before. :func:`bind_runs` then moves the S runs' tensors into one
stacked tensor ``[S, *shape]`` and makes every run's tensor a view of its slice: the modules keep
their identity, their values are the stacked tensor's. An update of ``RunDDPGUpdate`` or
``RunRCEUpdate`` computes the losses of the runs that acted in one pass of batched products (run
``s`` sees only its own parameters and its own sample), takes one :class:`~torchrl_reset.many.RunMaskedAdam`
step and one :class:`~torchrl_reset.many.RunMaskedSoftUpdate` for those runs, and leaves every other
run's parameters, targets and optimizer state exactly as they were.

The losses are the single-run losses, per run: :class:`~torchrl.objectives.DDPGLoss` (TD(0) target,
squared error, means over the batch and the members) and :class:`~torchrl_reset.RCELoss` (Eq. 2-3,
built from the same :func:`~torchrl_reset.rce_loss.shared_label`, :func:`~torchrl_reset.label_weight`,
:func:`~torchrl_reset.rce_loss.classifier_loss` and :func:`~torchrl_reset.rce_loss.actor_loss`). They
agree with the run alone to float32 rounding, not bit for bit: batched products sum in another order
(``tests/test_run_agents.py``).
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import TanhModule

from ..accel.ensemble import members_head as _head, members_trunk as _trunk
from ..ensemble import EnsembleValueOperator, with_prior
from ..rce_loss import actor_loss, classifier_loss, label_weight, shared_label
from .optim import RunMaskedAdam, RunMaskedSoftUpdate

__all__ = ["bind_runs", "RunPolicies", "RunEnsembles", "RunDDPGUpdate", "RunRCEUpdate"]


def bind_runs(tensors: Sequence[torch.Tensor], *, trainable: bool = False) -> torch.Tensor:
    """One ``[S, *shape]`` tensor holding the S runs' tensors; each run's tensor becomes a view of its slice.

    The run tensors stay the same Python objects (a module, its loss, its optimizer still hold them);
    only their storage moves (``tensor.data = stacked[s]``). Writing into the stacked tensor writes
    into every run's, and the reverse. ``trainable=True`` returns an ``nn.Parameter``.
    """
    tensors = list(tensors)
    shapes = {tuple(t.shape) for t in tensors}
    if not tensors or len(shapes) != 1:
        raise ValueError(f"bind_runs needs one or more tensors of one shape, got shapes {sorted(shapes)}.")
    stacked = torch.stack([t.detach() for t in tensors]).contiguous()
    if trainable:
        stacked = nn.Parameter(stacked)
    for s, t in enumerate(tensors):
        t.data = stacked.data[s]
    return stacked


def _select(stacked: torch.Tensor, runs: torch.Tensor | None) -> torch.Tensor:
    return stacked if runs is None else stacked[runs]


class RunPolicies:
    """S runs' policies (the recipe's ReLU MLP then :class:`~torchrl.modules.TanhModule`) as one.

    Args:
        actors: one policy module per run, each holding its ``nn.Linear`` layers in order and one
            ``TanhModule`` (the recipe's :func:`make_actor`), reading one observation key.
        targets: optional, per run, the target copy's parameters in the loss module's naming
            (``loss.target_actor_network_params``); bound too, for a delayed actor.
    """

    def __init__(self, actors: Sequence[nn.Module], targets: Sequence[TensorDictBase] | None = None) -> None:
        self.runs = len(actors)
        layers = [[(name, m) for name, m in actor.named_modules() if isinstance(m, nn.Linear)] for actor in actors]
        tanh = [m for m in actors[0].modules() if isinstance(m, TanhModule)]
        leaves = {type(m) for actor in actors for m in actor.modules() if not list(m.children())}
        if (not layers[0] or len(tanh) != 1 or len({len(x) for x in layers}) != 1
                or not leaves <= {nn.Linear, nn.ReLU, TanhModule}):
            raise ValueError("RunPolicies needs S policies of the same ReLU MLP layout ending in one TanhModule "
                             f"(the recipe's make_actor); got modules {sorted(t.__name__ for t in leaves)}.")
        self.tanh = tanh[0]
        self.preactivation_key = self.tanh.in_keys[0]
        self.action_key = self.tanh.out_keys[0]
        in_keys = list(dict.fromkeys(actors[0].in_keys))
        if len(in_keys) != 1:
            raise ValueError(f"RunPolicies reads one observation key; the policy reads {in_keys}.")
        self.in_key = in_keys[0]
        depth = len(layers[0])
        self.weights = [bind_runs([run[i][1].weight for run in layers], trainable=True) for i in range(depth)]
        self.biases = [bind_runs([run[i][1].bias for run in layers], trainable=True) for i in range(depth)]
        self.target_weights = self.target_biases = None
        if targets is not None:
            names = [name for name, _ in layers[0]]

            def target(i: int, kind: str) -> list[torch.Tensor]:
                return [t.get(tuple(names[i].split(".")) + (kind,)) for t in targets]

            self.target_weights = [bind_runs(target(i, "weight")) for i in range(depth)]
            self.target_biases = [bind_runs(target(i, "bias")) for i in range(depth)]
        self.id_to_slot = {id(run[i][1].weight): (self.weights[i], s) for s, run in enumerate(layers) for i in range(depth)}
        self.id_to_slot.update({id(run[i][1].bias): (self.biases[i], s) for s, run in enumerate(layers) for i in range(depth)})

    def parameters(self) -> list[nn.Parameter]:
        return [*self.weights, *self.biases]

    def __call__(self, observation: torch.Tensor, runs: torch.Tensor | None = None, *, target: bool = False) -> torch.Tensor:
        """The actions ``[S', N, a]`` of runs ``runs`` (all when None) on their observations ``[S', N, d]``."""
        weights = self.target_weights if target else self.weights
        biases = self.target_biases if target else self.biases
        if weights is None:
            raise ValueError("these policies have no target copy.")
        h, last = observation, len(weights) - 1
        for i, (w, b) in enumerate(zip(weights, biases)):
            w, b = _select(w, runs), _select(b, runs)
            h = torch.baddbmm(b.unsqueeze(1), h, w.transpose(1, 2))  # nn.Linear: x @ W^T + b, per run
            if i < last:
                h = h.relu()
        td = TensorDict({self.preactivation_key: h}, batch_size=h.shape[:-1])
        return self.tanh(td).get(self.action_key)


    def act(self, observation: torch.Tensor) -> torch.Tensor:
        """Row ``s`` of ``observation`` ``[S, d]`` by run ``s``'s policy, computed as that policy computes one
        observation alone (one ``F.linear`` per layer and row: the kernels ``nn.Linear`` runs on one
        observation), so the actions are bit for bit those of the runs alone; ``[S, a]``."""
        rows = []
        last = len(self.weights) - 1
        for s in range(observation.shape[0]):
            h = observation[s]
            for i, (w, b) in enumerate(zip(self.weights, self.biases)):
                h = nn.functional.linear(h, w[s], b[s])
                if i < last:
                    h = h.relu()
            rows.append(h)
        td = TensorDict({self.preactivation_key: torch.stack(rows)}, batch_size=[observation.shape[0]])
        return self.tanh(td).get(self.action_key)

    def module(self, out_key: str = "action") -> TensorDictModule:
        """The S runs' policies acting on a batch of S rows, row ``s`` by run ``s`` (one env copy per
        run, :class:`~torchrl_reset.BatchedDualCollector`): ``[S, d]`` observations to ``[S, a]``
        actions, bit for bit those of the runs alone (:meth:`act`)."""
        return TensorDictModule(self.act, in_keys=[self.in_key], out_keys=[out_key])


_TRAINED = ("weight_{}", "bias_{}")


def _per_member(x: torch.Tensor, k: int) -> torch.Tensor:
    """``[S', N, *]`` -> ``[S' * k, N, *]``: each run's rows for each of its k members."""
    runs, n = x.shape[0], x.shape[1]
    return x.unsqueeze(1).expand(runs, k, *x.shape[1:]).reshape(runs * k, n, x.shape[-1])


class RunEnsembles:
    """S runs' :class:`~torchrl_reset.EnsembleValueOperator` ensembles of K members, as S*K members.

    Member ``i`` of run ``s`` computes ``f_i(s, a) + beta * g_i(s, a)`` on run ``s``'s rows only, with
    the accelerator's products (:mod:`torchrl_reset.accel.ensemble`: fused biases, the one-wide logit
    layer as dot products, trained and prior members as one stack without gradients).

    Args:
        ensembles: one ensemble per run (same sizes and prior scale).
        targets: optional, per run, the target copy's tensors by name (``loss.target_value_network_params``
            or ``loss.target_classifier_network_params``).
    """

    #: up to this many rows per run (acting: one row), trained and prior members run as two stacks: joining
    #: them would copy every weight once per call, which costs more than it saves on so few rows
    SEPARATE_PRIOR_ROWS = 16

    def __init__(self, ensembles: Sequence[EnsembleValueOperator], targets: Sequence[TensorDictBase] | None = None) -> None:
        first = ensembles[0]
        self.template, self.runs, self.members = first, len(ensembles), first.num_members
        self.prior_scale, self.num_layers = first.prior_scale, first.num_layers
        self.trained_names = [n.format(i) for i in range(first.num_layers) for n in _TRAINED] + ["action_weight"]
        self.prior_names = ["prior_" + n for n in self.trained_names] if first.has_prior else []
        self.live = {n: bind_runs([getattr(e, n) for e in ensembles], trainable=True) for n in self.trained_names}
        # the priors never change: their stacks are copies (live and target priors are equal)
        self.priors = {n: torch.stack([getattr(e, n).detach() for e in ensembles]) for n in self.prior_names}
        self.target = None
        if targets is not None:
            self.target = {n: bind_runs([t.get(n) for t in targets]) for n in self.trained_names}
        self.id_to_slot = {id(getattr(e, n)): (self.live[n], s) for s, e in enumerate(ensembles) for n in self.trained_names}

    def parameters(self) -> list[nn.Parameter]:
        return list(self.live.values())

    def _layers(self, tensors: dict, runs: torch.Tensor | None, *, prefix: str = "", detach: bool = False):
        """Weights, biases and action weight of the selected runs, ``[S' K, ...]``."""
        def get(name: str) -> torch.Tensor:
            value = _select(tensors[prefix + name], runs)
            return (value.detach() if detach else value).reshape(-1, *value.shape[2:])

        return ([get(f"weight_{i}") for i in range(self.num_layers)], [get(f"bias_{i}") for i in range(self.num_layers)],
                get("action_weight"))

    def logits(self, observation: torch.Tensor, action: torch.Tensor, runs: torch.Tensor | None = None, *,
               target: bool = False, detach: bool = False) -> torch.Tensor:
        """Each run's members' logits ``[S', N, K]`` on its own ``observation`` ``[S', N, d]`` and ``action``.

        ``target``: the target copy; ``detach``: the parameters held fixed (gradient reaches the action only)."""
        if target and self.target is None:
            raise ValueError("these ensembles have no target copy.")
        count, n, k = observation.shape[0], observation.shape[1], self.members
        layers = self._layers(self.target if target else self.live, runs, detach=detach)
        action = action.to(observation.dtype)
        if not self.prior_names:
            out = _head(_trunk(_per_member(observation, k), *layers[:2]), _per_member(action, k), *layers)
            return out.reshape(count, k, n).transpose(1, 2)
        priors = self._layers(self.priors, runs, prefix="prior_")
        if torch.is_grad_enabled() or n <= self.SEPARATE_PRIOR_ROWS:
            x, a = _per_member(observation, k), _per_member(action, k)
            f = _head(_trunk(x, *layers[:2]), a, *layers)
            g = _head(_trunk(x, *priors[:2]), a, *priors)  # frozen: gradient reaches the action only
            return with_prior(f, g, self.prior_scale).reshape(count, k, n).transpose(1, 2)
        # without gradients, on many rows, each run's trained and prior members run as one stack of 2K
        def both(trained: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
            return torch.cat([trained.reshape(count, k, *trained.shape[1:]), prior.reshape(count, k, *prior.shape[1:])],
                             1).reshape(count * 2 * k, *trained.shape[1:])

        stacked = ([both(w, p) for w, p in zip(layers[0], priors[0])], [both(b, p) for b, p in zip(layers[1], priors[1])],
                   both(layers[2], priors[2]))
        out = _head(_trunk(_per_member(observation, 2 * k), *stacked[:2]), _per_member(action, 2 * k), *stacked,
                    overwrite=True).reshape(count, 2 * k, n)
        return with_prior(out[:, :k], out[:, k:], self.prior_scale).transpose(1, 2)

    def module(self, out_key: str | None = None) -> TensorDictModule:
        """The S runs' ensembles scoring a batch of S rows, row ``s`` by run ``s``'s K members (the trigger's
        model over one env copy per run): ``observation`` ``[S, d]`` and ``action`` ``[S, a]`` to ``[S, K]``.
        ``out_key`` defaults to the ensembles' own output key."""
        key = out_key or self.template.out_keys[0]
        return TensorDictModule(lambda obs, act: self.logits(obs.unsqueeze(1), act.unsqueeze(1)).squeeze(1),
                                in_keys=list(self.template.in_keys), out_keys=[key])

    def paired(self, observation: torch.Tensor, action: torch.Tensor, policy_action: torch.Tensor, start: int,
               runs: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Per run, the logits of ``(observation, action)`` (gradient to the trained parameters) and of
        ``(observation[:, start:], policy_action)`` (the parameters held fixed: gradient to the action
        only), sharing the members' state part: :meth:`~torchrl_reset.accel.FastEnsembleValueOperator.paired_logits`
        for S runs. Returns ``[S', N, K]`` and ``[S', N - start, K]``."""
        count, n, k = observation.shape[0], observation.shape[1], self.members
        x = _per_member(observation, k)
        act, policy_act = _per_member(action.to(observation.dtype), k), _per_member(policy_action.to(observation.dtype), k)
        weights, biases, action_weight = self._layers(self.live, runs)
        trunk = _trunk(x, weights, biases)
        held = [w.detach() for w in weights], [b.detach() for b in biases], action_weight.detach()
        policy = _head(trunk[:, start:].detach(), policy_act, *held)
        out = _head(trunk, act, weights, biases, action_weight, overwrite=True)  # after the policy's head
        if self.prior_names:
            priors = self._layers(self.priors, runs, prefix="prior_")
            with torch.no_grad():
                prior_trunk = _trunk(x, *priors[:2])
            policy = with_prior(policy, _head(prior_trunk[:, start:], policy_act, *priors), self.prior_scale)
            with torch.no_grad():
                prior = _head(prior_trunk, act, *priors, overwrite=True)
            out = with_prior(out, prior, self.prior_scale)
        return out.reshape(count, k, n).transpose(1, 2), policy.reshape(count, k, n - start).transpose(1, 2)


def _trained(group: dict, id_to_slot: dict) -> list[torch.Tensor]:
    """A per-run optimizer group's trained parameters (torchrl hands fixed buffers, such as the tanh's
    bounds, to the optimizer too; they never get a gradient)."""
    out = []
    for p in group["params"]:
        if id(p) in id_to_slot:
            out.append(p)
        elif p.requires_grad:
            raise ValueError(f"a trained parameter of shape {tuple(p.shape)} is in no batched network.")
    return out


def _adam_from(optimizers: Sequence[torch.optim.Optimizer], id_to_slot: dict, runs: int) -> RunMaskedAdam:
    """A :class:`RunMaskedAdam` with the per-run optimizers' groups (lr, betas, eps) and their state."""
    groups = []
    for group in optimizers[0].param_groups:
        stacked = {id(id_to_slot[id(p)][0]): id_to_slot[id(p)][0] for p in _trained(group, id_to_slot)}
        groups.append({"params": list(stacked.values()), "lr": group["lr"], "betas": group["betas"], "eps": group["eps"]})
    adam = RunMaskedAdam(groups, runs=runs)
    load_run_optimizers(adam, optimizers, id_to_slot)
    return adam


def load_run_optimizers(adam: RunMaskedAdam, optimizers: Sequence[torch.optim.Optimizer], id_to_slot: dict) -> None:
    """Copies each run's torch Adam state (moments, step count) into its slice of ``adam``."""
    counts = {}
    for s, opt in enumerate(optimizers):
        for group in opt.param_groups:
            for p in _trained(group, id_to_slot):
                stacked, slot = id_to_slot[id(p)]
                state = opt.state.get(p)
                if not state:
                    continue
                adam.state[stacked]["exp_avg"][slot].copy_(state["exp_avg"])
                adam.state[stacked]["exp_avg_sq"][slot].copy_(state["exp_avg_sq"])
                counts.setdefault(s, set()).add(int(float(state["step"])))
    for s, steps in counts.items():
        if len(steps) != 1:
            raise ValueError(f"run {s}'s optimizer holds parameters at different step counts {sorted(steps)}.")
        adam.steps[s] = steps.pop()


def export_run_optimizer(adam: RunMaskedAdam, optimizer: torch.optim.Optimizer, id_to_slot: dict, run: int) -> None:
    """Writes run ``run``'s slice of ``adam`` into its own torch Adam, as that optimizer would hold it alone."""
    steps = int(adam.steps[run])
    for group in optimizer.param_groups:
        for p in _trained(group, id_to_slot):
            stacked, slot = id_to_slot[id(p)]
            if steps == 0:
                optimizer.state.pop(p, None)
                continue
            old = optimizer.state.get(p, {})
            step = old.get("step")
            like = step if isinstance(step, torch.Tensor) else torch.tensor(0.0)
            optimizer.state[p] = {"step": torch.full_like(like, float(steps)),
                                  "exp_avg": adam.state[stacked]["exp_avg"][slot].clone(),
                                  "exp_avg_sq": adam.state[stacked]["exp_avg_sq"][slot].clone()}


def _mask(runs: torch.Tensor, count: int) -> torch.Tensor:
    mask = torch.zeros(count, dtype=torch.bool)
    mask[runs] = True
    return mask


def _key(key) -> tuple:
    return (key,) if isinstance(key, str) else tuple(key)


def _stack(samples: Sequence[TensorDictBase], key) -> torch.Tensor:
    return torch.stack([s.get(key) for s in samples])


class _RunUpdate:
    """What both updates share: the policies, the ensembles, one masked Adam, the masked target updates."""

    loss_names: tuple[str, str]

    def __init__(self, policies: RunPolicies, ensembles: RunEnsembles, optimizers: Sequence[torch.optim.Optimizer],
                 tau: float) -> None:
        self.policies, self.ensembles, self.runs = policies, ensembles, policies.runs
        self.optimizers = list(optimizers)
        self.id_to_slot = {**policies.id_to_slot, **ensembles.id_to_slot}
        self.optimizer = _adam_from(self.optimizers, self.id_to_slot, self.runs)
        sources, targets = [], []
        if policies.target_weights is not None:
            sources += [*policies.weights, *policies.biases]
            targets += [*policies.target_weights, *policies.target_biases]
        if ensembles.target is not None:
            sources += [ensembles.live[n] for n in ensembles.trained_names]
            targets += [ensembles.target[n] for n in ensembles.trained_names]
        self.targets = RunMaskedSoftUpdate(sources, targets, self.runs, tau)

    def losses(self, samples: Sequence[TensorDictBase], runs: torch.Tensor) -> dict[str, torch.Tensor]:
        """Both losses per run, computed together (the joint step)."""
        raise NotImplementedError

    def critic_losses(self, samples: Sequence[TensorDictBase], runs: torch.Tensor | None) -> torch.Tensor:
        """The critic's loss per run (``loss_names[1]``), alone."""
        raise NotImplementedError

    def actor_losses(self, samples: Sequence[TensorDictBase], runs: torch.Tensor | None) -> torch.Tensor:
        """The actor's loss per run, the critic held fixed, alone."""
        raise NotImplementedError

    @staticmethod
    def _check_finite(index: torch.Tensor, losses: dict[str, torch.Tensor]) -> torch.Tensor:
        total = sum(losses.values())
        finite = torch.isfinite(total.detach())
        if not bool(finite.all()):
            bad = index[~finite].tolist()
            raise FloatingPointError(f"runs {bad}: " + ", ".join(
                f"{n}={v.detach()[~finite].tolist()}" for n, v in losses.items()))
        return total

    def _step(self, total: torch.Tensor, mask: torch.Tensor, *, same_step: bool = False) -> None:
        self.optimizer.zero_grad()
        total.sum().backward()  # the runs' parameters are disjoint: each gets its own loss's gradient
        self.optimizer.step(mask, same_step=same_step)

    def update(self, samples: Sequence[TensorDictBase], runs: Sequence[int], *,
               actor_rows: Sequence[torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        """One update and one target update for the runs ``runs`` (sample ``samples[j]`` is run ``runs[j]``'s);
        returns each loss per run, ``[len(runs)]``. Raises ``FloatingPointError`` naming the runs whose
        loss is not finite, before any parameter that loss moves changed.

        Without ``actor_rows``: one step on the sum of both losses computed together. With ``actor_rows``
        (one index tensor per run, the rows of its sample drawn with replacement, as the run alone draws
        them): the authors' release's order (``update_order: release``), as ``recipes/train.py``'s
        ``update`` runs it for one run: a step on the critic's loss, then a step on the actor's loss over
        ``samples[j][actor_rows[j]]`` computed with the updated critic, then the target update. The
        two steps move disjoint parameters, each once: a run's Adam step count advances once, as torch's
        per-parameter counts do."""
        index = torch.as_tensor(list(runs), dtype=torch.long)
        if index.numel() == 0:
            return {}
        everyone = index.numel() == self.runs and bool((index == torch.arange(self.runs)).all())
        selected, mask = None if everyone else index, _mask(index, self.runs)
        actor_name, critic_name = self.loss_names
        if actor_rows is None:
            losses = self.losses(samples, selected)
            self._step(self._check_finite(index, losses), mask)
        else:
            if len(actor_rows) != len(samples):
                raise ValueError(f"actor_rows gives {len(actor_rows)} index tensors for {len(samples)} samples.")
            critic = self.critic_losses(samples, selected)
            self._step(self._check_finite(index, {critic_name: critic}), mask)
            actor = self.actor_losses([s[rows] for s, rows in zip(samples, actor_rows)], selected)
            self._step(self._check_finite(index, {actor_name: actor}), mask, same_step=True)
            losses = {actor_name: actor, critic_name: critic}
        self.targets.step(mask)
        return {n: v.detach() for n, v in losses.items()}

    def export(self, run: int) -> None:
        """Run ``run``'s optimizer state into its own optimizer (before its checkpoint)."""
        export_run_optimizer(self.optimizer, self.optimizers[run], self.id_to_slot, run)


class RunDDPGUpdate(_RunUpdate):
    """DDPG for S runs: the forward agent (K = 1) or LNT's reset agent (a K-member Q ensemble).

    Per run, as :class:`~torchrl.objectives.DDPGLoss` with the TD(0) estimator computes it:
    ``loss_value = mean (Q_i(s, a) - r - gamma (1 - terminated) Q'_i(s', pi'(s')))^2`` over the
    batch and the members, ``loss_actor = -mean Q_i(s, pi(s))`` with the critic held fixed. Where the
    losses' estimator is a :class:`~torchrl_reset.BoundedTD0Estimator` the targets are clipped as it
    clips them.

    Args:
        losses: the runs' DDPG loss modules (their networks and target copies are bound).
        optimizers: the runs' Adam optimizers (groups: actor, then critic).
        gamma, tau: the discount and the target update rate.
        reward_key: the reward entry under ``"next"`` (``"lnt_reward"`` for LNT's reset agent).
    """

    loss_names = ("loss_actor", "loss_value")

    def __init__(self, losses: Sequence, optimizers: Sequence[torch.optim.Optimizer], *, gamma: float, tau: float,
                 reward_key="reward") -> None:
        policies = RunPolicies([loss.actor_network for loss in losses], [loss.target_actor_network_params for loss in losses])
        ensembles = RunEnsembles([loss.value_network for loss in losses], [loss.target_value_network_params for loss in losses])
        self.gamma, self.reward_key = float(gamma), reward_key
        bounds = {getattr(loss.value_estimator, "bounds", None) for loss in losses}  # BoundedTD0Estimator's
        if len(bounds) > 1:
            raise ValueError(f"the runs' TD target bounds differ ({sorted(map(str, bounds))}); batch runs that share them.")
        self.bounds = bounds.pop()
        self.obs_key = policies.in_key
        super().__init__(policies, ensembles, optimizers, tau)

    def losses(self, samples: Sequence[TensorDictBase], runs: torch.Tensor | None) -> dict[str, torch.Tensor]:
        loss_value = self.critic_losses(samples, runs)
        return {"loss_actor": self.actor_losses(samples, runs), "loss_value": loss_value}

    def critic_losses(self, samples: Sequence[TensorDictBase], runs: torch.Tensor | None) -> torch.Tensor:
        obs = _stack(samples, self.obs_key)
        action = _stack(samples, "action")
        next_obs = _stack(samples, ("next", self.obs_key))
        reward = _stack(samples, ("next", self.reward_key))
        terminated = _stack(samples, ("next", "terminated"))
        q = self.ensembles.logits(obs, action, runs)  # [S', B, K]
        with torch.no_grad():
            next_q = self.ensembles.logits(next_obs, self.policies(next_obs, runs, target=True), runs, target=True)
            target = reward + self.gamma * (~terminated).int() * next_q
            if self.bounds is not None:
                target = target.clamp(*self.bounds)
        return (q - target).pow(2).flatten(1).mean(1)

    def actor_losses(self, samples: Sequence[TensorDictBase], runs: torch.Tensor | None) -> torch.Tensor:
        obs = _stack(samples, self.obs_key)
        actor_q = self.ensembles.logits(obs, self.policies(obs, runs), runs, detach=True)
        return -actor_q.flatten(1).mean(1)


class RunRCEUpdate(_RunUpdate):
    """RCE for S runs' reset agents (ours): :class:`~torchrl_reset.RCELoss`'s Eq. 2-3 per run.

    Args:
        losses: the runs' RCE loss modules (their actors, classifier ensembles and target classifiers).
        optimizers: the runs' Adam optimizers (groups: actor, then classifier).
        tau: the target update rate.
    """

    loss_names = ("loss_actor", "loss_classifier")

    def __init__(self, losses: Sequence, optimizers: Sequence[torch.optim.Optimizer], *, tau: float) -> None:
        first = losses[0]
        policies = RunPolicies([loss.actor_network for loss in losses])
        ensembles = RunEnsembles([loss.classifier_network for loss in losses],
                                 [loss.target_classifier_network_params for loss in losses])
        self.gamma, self.n_steps, self.clip = float(first.gamma), int(first.n_steps), bool(first.clip_target_values)
        keys = first.tensor_keys
        self.obs_key, self.nstep_key, self.example_key = policies.in_key, keys.nstep_state, keys.example_state
        self.one_step_key = keys.one_step
        if [_key(k) for k in ensembles.template.in_keys[:-1]] != [_key(self.obs_key)]:
            raise ValueError(f"RunRCEUpdate needs the classifier to read the policy's observation {self.obs_key!r} "
                             f"only; it reads {ensembles.template.in_keys[:-1]}.")
        super().__init__(policies, ensembles, optimizers, tau)

    def _targets(self, samples: Sequence[TensorDictBase]) -> torch.Tensor:
        """``s_{t+1}`` (and ``s_{t+n}`` when n > 1) of each run, ``[S', B or 2B, d]``."""
        states = [_stack(samples, ("next", self.obs_key))]
        if self.n_steps > 1:
            states.append(_stack(samples, (*_key(self.nstep_key), self.obs_key)))
        return torch.cat(states, 1)

    def _labels_from(self, samples, targets: torch.Tensor, actions: torch.Tensor, runs) -> tuple[torch.Tensor, torch.Tensor]:
        gamma, batch = self.gamma, samples[0].shape[0]
        value = torch.sigmoid(self.ensembles.logits(targets, actions, runs, target=True))
        nstep = one_step = None
        if self.n_steps > 1:
            nstep = value[:, batch:]
            one_step = torch.tensor([bool(s.get(self.one_step_key, torch.zeros(1, dtype=torch.bool)).all())
                                     for s in samples], device=value.device).reshape(-1, 1, 1)
        label = shared_label(value[:, :batch], gamma, nstep, self.n_steps, clip_values=self.clip, one_step=one_step)
        return label, label_weight(label, gamma)

    def labels(self, samples: Sequence[TensorDictBase], runs: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Each run's shared label ``y`` and weight ``1 + gamma w_y``, ``[S', B]``, without gradient."""
        with torch.no_grad():
            targets = self._targets(samples)
            return self._labels_from(samples, targets, self.policies(targets, runs), runs)

    def _classifier_inputs(self, samples: Sequence[TensorDictBase], runs: torch.Tensor | None):
        """Eq. 2's pairs, the examples' then the replay rows' (states and actions, ``[S', 2B, ...]``), with
        the shared label and weight; one policy pass, without gradient, for s_{t+1}, s_{t+n} and s*."""
        obs = _stack(samples, self.obs_key)
        action = _stack(samples, "action")
        examples = _stack(samples, (*_key(self.example_key), self.obs_key))
        with torch.no_grad():
            targets = self._targets(samples)
            acting = self.policies(torch.cat([targets, examples], 1), runs)
            label, weight = self._labels_from(samples, targets, acting[:, :targets.shape[1]], runs)
            example_action = acting[:, targets.shape[1]:]
        states = torch.cat([examples, obs], 1)
        return obs, states, torch.cat([example_action, action.to(example_action.dtype)], 1), label, weight

    def losses(self, samples: Sequence[TensorDictBase], runs: torch.Tensor | None) -> dict[str, torch.Tensor]:
        batch = samples[0].shape[0]
        obs, states, actions, label, weight = self._classifier_inputs(samples, runs)
        # the examples' and replay rows' classifier pairs and the actor's pairs share the state part
        logits, actor_logits = self.ensembles.paired(states, actions, self.policies(obs, runs), batch, runs)
        return {"loss_actor": actor_loss(actor_logits),
                "loss_classifier": classifier_loss(logits[:, :batch], logits[:, batch:], label, weight, self.gamma)}

    def critic_losses(self, samples: Sequence[TensorDictBase], runs: torch.Tensor | None) -> torch.Tensor:
        """Eq. 2 per run alone (the release's order: before the actor's step)."""
        batch = samples[0].shape[0]
        _, states, actions, label, weight = self._classifier_inputs(samples, runs)
        logits = self.ensembles.logits(states, actions, runs)
        return classifier_loss(logits[:, :batch], logits[:, batch:], label, weight, self.gamma)

    def actor_losses(self, samples: Sequence[TensorDictBase], runs: torch.Tensor | None) -> torch.Tensor:
        """Eq. 3 per run alone, the classifiers held fixed."""
        obs = _stack(samples, self.obs_key)
        return actor_loss(self.ensembles.logits(obs, self.policies(obs, runs), runs, detach=True))
