"""What a configuration without a key ran with.

The keys that made the recipe follow the authors' release (commit ``d7b4986``) arrived with the earlier
behaviour as their fallback: a run whose ``config.yaml`` predates them resumes as it ran, and the report
reads its settings the same way. The paper preset (``conf/``) sets today's values; this table holds what
the absence of each key means, in one place for the training code and the report.
"""
from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

__all__ = ["ABSENT_KEYS", "setting"]

#: key -> the behaviour of a configuration without it (the recipe's behaviour before the key existed)
ABSENT_KEYS = {
    "algo.prior_bias_draw": "fan_in",      # the priors' biases U(+-1/sqrt(fan_in)) (the release: xavier)
    "exploration.restart": "episode",      # the noise restarted at every episode (the release: never)
    "exploration.clip": True,              # the noisy action projected onto the action box (the release: false)
    "update_order": "joint",               # one step on both losses (the release: critic, then actor)
    "forward.sampling": "transition",      # the forward buffer uniform over steps (the release: episode first)
    "target_init": "copy",                 # every target a copy of its network (the release's draws: release)
    "algo.success_terminal": False,        # LNT's TD targets bootstrap through a successful reset (as the preset)
    "algo.independent_batches": False,     # LNT: one batch shared by the members (the authors' K critics: one each)
    "algo.member_actor_gradient": False,   # LNT: the actor ascends the members' mean
    "algo.target_draws": False,            # LNT: every target a copy at the start
    "algo.sampling": "transition",         # LNT: the reset buffer uniform over steps
    "reset.actor.head": "tanh",            # the reset actor: the release's deterministic tanh head ...
    "reset.actor.preact_penalty": 0.0,     # ... with nothing added to its loss
    "reset.actor.action_l2": 0.0,
    "reset.actor.entropy": 0.0001,         # (read by the tanh_normal head only: RCE's fixed coefficient)
    "reset.learn_from_forward": False,     # the reset agent's buffer: reset transitions only (the paper's B_r)
    "learner.streams": "shared",           # one random stream for acting and learning
    "learner.mode": "sync",                # one process acts and learns
    "learner.max_lag": 0,
    "learner.timeout": 60,
}


def setting(cfg: DictConfig, key: str):
    """``cfg``'s value for ``key``, or what a configuration without it ran with (:data:`ABSENT_KEYS`)."""
    return OmegaConf.select(cfg, key, default=ABSENT_KEYS[key])
