"""The reset agent, described once per kind: ours (RCE on a classifier ensemble with priors, trained from
examples) and LNT / LNT-sparse (DDPG on a Q ensemble, trained from a reward).

Everything in the recipe that differs between the two kinds is a method of :class:`ResetAgentKind`: the
loss and its networks, what the replay buffer keeps and how it is sampled, how a sample is completed
before the update (success examples, or the reward), the trigger's score and threshold, and the
configuration keys that only one kind reads. The rest of the recipe reads the kind from the run's spec
(:class:`~.run_spec.RunSpec`) and never compares the algorithm's name.
"""
from __future__ import annotations

import math

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer

from torchrl_reset_recipes.training.absent_keys import ABSENT_KEYS, setting
from torchrl_reset import EpisodeWindowSampler, NStepStateTransform, ResetTriggerTransform, success_probability
from torchrl_reset.ensemble import PRIOR_BIAS_DRAWS
from torchrl_reset.ensemble_ddpg import EnsembleDDPGLoss
from torchrl_reset.stochastic_actor import EntropyDDPGLoss
from torchrl_reset.td_bounds import bound_td0_targets

__all__ = ["ResetAgentKind", "RCEKind", "LNTKind", "KINDS", "lnt_batch", "END_FLAGS"]

#: the episode's end flags, kept in every replay buffer (the losses' and the n-step transform's)
END_FLAGS = [("next", "done"), ("next", "terminated")]


def _nested(key) -> tuple:
    return (key,) if isinstance(key, str) else tuple(key)


class ResetAgentKind:
    """What one kind of reset agent is in this recipe (see the module's docstring)."""

    name: str
    #: the loss entry of its critic (the classifiers' or the Q-functions'), minimised beside ``loss_actor``
    critic_loss: str
    #: whether its trigger score is a success probability (ours) rather than a value (LNT's Q)
    scores_probability: bool
    #: how its trigger reduces the members' scores
    reduction: str
    #: its name in tables and figures, and its colour in the figures
    title: str
    color: str

    @property
    def threshold_name(self) -> str:
        """What its trigger's threshold is called: p_thresh (a success probability) or Q_thresh (a value)."""
        return "p_thresh" if self.scores_probability else "Q_thresh"

    @property
    def score_name(self) -> str:
        """What its trigger scores, in words."""
        return ("p: ensemble-mean success probability" if self.scores_probability
                else "Q: reset Q-ensemble's minimum")

    def build(self, spec, actor, obs_dim: int, act_dim: int, parts, head):
        """Its model (the ensemble) and loss module on ``actor`` (whose ``head`` gives the loss its arguments:
        a stochastic actor's temperature); returns ``(model, loss, param_groups)``."""
        raise NotImplementedError

    def fresh_targets(self, spec, loss, obs_dim: int, act_dim: int, parts, make_actor) -> list[tuple]:
        """Newly drawn networks whose parameters its loss's targets take at the start, as ``(network, name of
        those targets in the loss)``; empty where its targets stay copies. ``make_actor()`` draws a reset actor."""
        return []

    def replay(self, spec, size: int, batch_size: int | None) -> ReplayBuffer:
        """Its replay buffer of ``size`` rows."""
        raise NotImplementedError

    def buffer_keys(self, spec, agent) -> list[tuple]:
        """The entries its replay buffer keeps: what its loss reads (``loss.in_keys``; entries the sample gets
        later, such as the success examples, are not in a collected step and are skipped), its end flags,
        and what its buffer's own transform reads."""
        raise NotImplementedError

    def prepare(self, sample, info: dict, examples, spec):
        """Completes a replay sample for the loss (``info``: what the buffer's sampler returned)."""
        raise NotImplementedError

    def threshold(self, cfg: DictConfig) -> float:
        """The trigger's threshold for this run."""
        raise NotImplementedError

    def trigger(self, model, threshold) -> ResetTriggerTransform:
        """The reset trigger on ``model``."""
        raise NotImplementedError

    def member_scores(self, values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The model's outputs as ``(C, score)`` per member (diagnostics: C is NaN where it has no classifier)."""
        raise NotImplementedError

    def check(self, cfg: DictConfig) -> list[str]:
        """Problems with the configuration keys this kind reads (or must not be given)."""
        return []


class RCEKind(ResetAgentKind):
    """Ours: recursive classification of examples (RCE) on K classifiers with randomized priors."""

    name, critic_loss, scores_probability, reduction = "ours", "loss_classifier", True, "mean"
    title, color = "ours", "tab:red"

    def build(self, spec, actor, obs_dim, act_dim, parts, head):
        cfg = spec.cfg
        model = parts.ensemble(
            obs_dim, act_dim, num_members=cfg.algo.num_members, hidden_sizes=tuple(cfg.hidden_sizes),
            prior_scale=cfg.algo.prior_scale,
            prior_bias_draw=spec["algo.prior_bias_draw"],
        )
        _pessimistic_start(spec, model)  # not the paper's, when set; before the targets copy the networks
        loss = parts.rce_loss(actor, model, gamma=cfg.gamma, n_steps=cfg.algo.n_steps,
                              clip_target_values=bool(spec["algo.clip_target_values"]), **head.loss_kwargs())
        groups = [{"params": list(actor.parameters()), "lr": cfg.reset.actor_lr},
                  {"params": list(model.parameters()), "lr": cfg.reset.critic_lr}]  # the priors are buffers
        return model, loss, groups

    def fresh_targets(self, spec, loss, obs_dim, act_dim, parts, make_actor):
        # target_init: release: the target classifiers' trained part starts as networks of their own (the same
        # priors); RCE never reads the reset actor's target
        if spec["target_init"] != "release":
            return []
        cfg = spec.cfg
        fresh = parts.ensemble(obs_dim, act_dim, num_members=cfg.algo.num_members,
                               hidden_sizes=tuple(cfg.hidden_sizes), prior_scale=0.0)
        _pessimistic_start(spec, fresh)  # the pessimistic start's output bias holds for the targets too
        return [(fresh, "target_classifier_network_params")]

    def replay(self, spec, size, batch_size):
        # the n-step state beside the next state; with algo.nstep_sampling: episode (the release), episodes
        # first, then a window of n steps inside one
        episodes, n = spec["algo.nstep_sampling"] == "episode", spec.cfg.algo.n_steps
        return ReplayBuffer(storage=LazyTensorStorage(size), batch_size=batch_size,
                            transform=NStepStateTransform(n), sampler=EpisodeWindowSampler(n) if episodes else None)

    def buffer_keys(self, spec, agent):
        # the n-step transform reads the trajectory id beside the end flags
        return [*map(_nested, agent.loss.in_keys), *END_FLAGS, ("collector", "traj_ids")]

    def prepare(self, sample, info, examples, spec):
        if info.get("fallback", False):  # no reset episode has n transitions yet: the release's one-step label
            sample.set("one_step", torch.ones(sample.shape[0], dtype=torch.bool, device=sample.device))
        sample.set("example", examples.sample(sample.shape[0]).to(spec.cfg.device))  # as many success examples
        return sample

    def threshold(self, cfg):
        return float(cfg.task.p_thresh if cfg.algo.threshold is None else cfg.algo.threshold)

    def trigger(self, model, threshold):
        return ResetTriggerTransform(model, threshold)

    def member_scores(self, values):
        return torch.sigmoid(values), success_probability(values)

    def check(self, cfg):
        problems = []
        if cfg.algo.threshold is not None and not 0.0 < float(cfg.algo.threshold) < 1.0:
            problems.append(f"algo.threshold (a success probability) must lie in (0, 1), got {cfg.algo.threshold}")
        if OmegaConf.select(cfg, "algo.reward_bounds", default=None) is not None:
            problems.append("algo.reward_bounds clips LNT's TD targets; ours has no reward (its labels: "
                            "algo.clip_target_values)")
        if OmegaConf.select(cfg, "algo.success_terminal", default=False):
            problems.append("algo.success_terminal ends LNT's TD targets at a successful reset; ours has no TD "
                            "targets on a reward")
        sampling = OmegaConf.select(cfg, "algo.nstep_sampling", default="episode")
        if sampling not in ("episode", "transition"):
            problems.append(f"algo.nstep_sampling must be episode or transition, got {sampling!r}")
        draw = setting(cfg, "algo.prior_bias_draw")
        if draw not in PRIOR_BIAS_DRAWS:
            problems.append(f"algo.prior_bias_draw must be one of {', '.join(PRIOR_BIAS_DRAWS)}, got {draw!r}")
        return problems


class LNTKind(ResetAgentKind):
    """LNT (shaped reward) and LNT-sparse (the success flag as its reward): DDPG on K Q-functions, without priors
    (``algo.prior_scale: 0``; the authors' K-critic DDPG class has none)."""

    critic_loss, scores_probability, reduction = "loss_value", False, "min"

    def __init__(self, name: str, title: str, color: str) -> None:
        self.name, self.title, self.color = name, title, color

    def build(self, spec, actor, obs_dim, act_dim, parts, head):
        cfg = spec.cfg
        model = parts.ensemble(
            obs_dim, act_dim, num_members=cfg.algo.num_members, hidden_sizes=tuple(cfg.hidden_sizes),
            prior_scale=cfg.algo.prior_scale, out_keys=["state_action_value"],
        )
        bounds = spec["algo.reward_bounds"]
        independent, per_member = spec["algo.independent_batches"], spec["algo.member_actor_gradient"]
        if independent or per_member:  # the authors' K-critic DDPG class (not the project's default LNT)
            loss = EnsembleDDPGLoss(actor, model, gamma=cfg.gamma, independent_batches=independent,
                                    member_actor_gradient=per_member, reward_key="lnt_reward",
                                    reward_bounds=None if bounds is None else tuple(bounds), **head.loss_kwargs())
        else:  # torchrl's DDPGLoss (with a stochastic actor's temperature where the head has one)
            loss = EntropyDDPGLoss(actor, model, delay_actor=True, delay_value=True, **head.loss_kwargs())
            loss.set_keys(reward="lnt_reward")  # written by prepare(): one column per member
            loss.make_value_estimator(gamma=cfg.gamma)
            if bounds is not None:  # not the paper's: TD targets clipped to the values these rewards allow
                bound_td0_targets(loss, tuple(bounds))
        groups = [{"params": list(loss.actor_network_params.values(True, True)), "lr": cfg.reset.actor_lr},
                  {"params": list(loss.value_network_params.values(True, True)), "lr": cfg.reset.critic_lr}]
        return model, loss, groups

    def fresh_targets(self, spec, loss, obs_dim, act_dim, parts, make_actor):
        # algo.target_draws (the release's constructors): the actor's target and every member's but the last
        # start as independent draws; the last member's target stays a copy (its constructor synced it last)
        if not spec["algo.target_draws"]:
            return []
        cfg = spec.cfg
        members = parts.ensemble(obs_dim, act_dim, num_members=cfg.algo.num_members,
                                 hidden_sizes=tuple(cfg.hidden_sizes), prior_scale=0.0,
                                 out_keys=["state_action_value"])
        with torch.no_grad():
            for key, value in TensorDict.from_module(members).items(True, True):
                value[-1].copy_(loss.value_network_params.get(key)[-1])
        return [(make_actor(), "target_actor_network_params"), (members, "target_value_network_params")]

    def replay(self, spec, size, batch_size):
        # algo.independent_batches: K batches per update, drawn as one of K * B rows (prepare() splits them);
        # algo.sampling: episode, the release's buffer: an episode first, then a step in it
        if spec["algo.independent_batches"]:
            batch_size = int(spec.cfg.algo.num_members) * batch_size
        episodes = spec["algo.sampling"] == "episode"
        return ReplayBuffer(storage=LazyTensorStorage(size), batch_size=batch_size,
                            sampler=EpisodeWindowSampler(1) if episodes else None)

    def buffer_keys(self, spec, agent):
        # its rows are single transitions; the reward comes from these two (and the episode-first sampler reads
        # the trajectory id)
        episodes = [("collector", "traj_ids")] if spec["algo.sampling"] == "episode" else []
        return [*map(_nested, agent.loss.in_keys), *END_FLAGS, ("next", "reset_reward"), ("next", "reset_success"),
                *episodes]

    def prepare(self, sample, info, examples, spec):
        members = int(spec.cfg.algo.num_members)
        if spec["algo.independent_batches"]:  # member k's batch at [k]
            sample = sample.reshape(members, -1)
        return lnt_batch(sample, spec.cfg.algo, members)

    def threshold(self, cfg):
        return float(cfg.algo.threshold)  # Q_thresh

    def trigger(self, model, threshold):
        return ResetTriggerTransform(model, threshold, score="value", reduction="min",
                                     model_out_key="state_action_value", score_key="reset_value")

    def member_scores(self, values):
        return torch.full_like(values, math.nan), values

    def check(self, cfg):
        bounds = OmegaConf.select(cfg, "algo.reward_bounds", default=None)
        if bounds is not None and (not OmegaConf.is_list(bounds) or len(bounds) != 2
                                   or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in bounds)
                                   or not bounds[0] < bounds[1]):
            return [f"algo.reward_bounds must be [low, high] with low < high, got {bounds!r}"]
        for key in ("algo.success_terminal", "algo.independent_batches", "algo.member_actor_gradient",
                    "algo.target_draws"):
            if not isinstance(setting(cfg, key), bool):
                return [f"{key} must be true or false, got {OmegaConf.select(cfg, key)!r}"]
        if setting(cfg, "algo.sampling") not in ("episode", "transition"):
            return [f"algo.sampling must be episode or transition, got {OmegaConf.select(cfg, 'algo.sampling')!r}"]
        return []


#: the algorithm registry: each algorithm's kind of reset agent, its title and colour, what its trigger scores
KINDS = {"ours": RCEKind(), "lnt": LNTKind("lnt", "LNT", "tab:blue"),
         "lnt_sparse": LNTKind("lnt_sparse", "LNT-sparse", "tab:green"),
         # LNT's ensemble as the authors' K-critic DDPG class runs it (algo.independent_batches and the rest on)
         "lnt_release": LNTKind("lnt_release", "LNT (release's ensemble)", "tab:cyan"),
         "lnt_sparse_release": LNTKind("lnt_sparse_release", "LNT-sparse (release's ensemble)", "tab:olive")}


def lnt_batch(sample, algo: DictConfig, num_members: int):
    """The LNT reset agent's batch: its reward (shaped or sparse) and done flags, one column per ensemble member.
    With ``algo.success_terminal`` (not the paper's) a step into the success check is terminal for the TD
    targets: ``Q = r`` there, no bootstrapping past it."""
    nxt = sample.get("next")
    reward = nxt.get("reset_reward") if algo.reset_reward == "shaped" else nxt.get("reset_success").float()
    shape = (*reward.shape[:-1], num_members)
    nxt.set("lnt_reward", reward.expand(shape))
    if OmegaConf.select(algo, "success_terminal", default=ABSENT_KEYS["algo.success_terminal"]):
        success = nxt.get("reset_success").reshape(nxt.get("terminated").shape)
        for key in ("done", "terminated"):
            nxt.set(key, nxt.get(key) | success)
    for key in ("done", "terminated"):
        nxt.set(key, nxt.get(key).expand(shape))
    return sample


def _pessimistic_start(spec, ensemble: nn.Module) -> None:
    """``algo.initial_logit_bias`` (not the paper's): the members' output bias set to it."""
    bias = spec["algo.initial_logit_bias"]
    if bias is not None:
        with torch.no_grad():
            getattr(ensemble, f"bias_{ensemble.num_layers - 1}").fill_(float(bias))
