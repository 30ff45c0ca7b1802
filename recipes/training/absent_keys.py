"""What a configuration without a key runs with: one table for the training code and the report.

Today's values are set by the configuration (``conf/`` and the task registry); this module holds what the
*absence* of a key means, which is history: for some keys it is today's value too (``FALLBACKS``), for others
the behaviour before the key existed (``ABSENT_KEYS``):

- :data:`ABSENT_KEYS`: the keys that changed what a run computes when they arrived (those that made the recipe
  follow the authors' release, commit ``d7b4986``, and later ones), each with the behaviour before it. A run whose
  ``config.yaml`` predates a key resumes as it ran, and the report labels it by what it ran.
- :data:`FALLBACKS`: the keys of today's configuration that code reading an older or hand-made configuration
  must still answer (speed settings, optional task entries); the report reads them as the recipe's defaults.
- :data:`DEFAULTS`: both, what :func:`~.run_spec.run_spec` reads every setting through.
"""
from __future__ import annotations

from types import MappingProxyType

from omegaconf import DictConfig, OmegaConf

__all__ = ["ABSENT_KEYS", "DEFAULTS", "FALLBACKS", "setting"]

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
    "forward.actor.head": "tanh",          # the forward actor: the paper's DDPG (deterministic tanh head) ...
    "forward.actor.preact_penalty": 0.0,   # ... with nothing added to its loss
    "forward.actor.action_l2": 0.0,
    "forward.actor.entropy": "auto",       # (read by the tanh_normal head only)
    "reset.learn_from_forward": False,     # the reset agent's buffer: reset transitions only (the paper's B_r)
    "learner.streams": "shared",           # one random stream for acting and learning
    "learner.mode": "sync",                # one process acts and learns
    "learner.max_lag": 0,
    "learner.timeout": 60,
}


#: settings that every configuration of today's recipe holds, and what code reading an older or hand-made
#: configuration without them uses (the report reads such runs through :data:`ABSENT_KEYS` alone)
FALLBACKS = {
    "speed.accelerate": True,
    "speed.fused_adam": False,
    "speed.retain_memory": True,
    "speed.matmul_precision": "ieee",
    "speed.compile": [],
    "keep_states_every": None,
    "reset.tau": None,                       # None: the shared tau
    "task.exploration": None,                # the task's own exploration.* entries (cliff-walker's)
    "algo.clip_target_values": False,
    "algo.nstep_sampling": "episode",
    "algo.reward_bounds": None,
    "algo.initial_logit_bias": None,
}
#: every setting with a default, in one table: what a configuration without the key runs with
DEFAULTS = MappingProxyType({**ABSENT_KEYS, **FALLBACKS})


def setting(cfg: DictConfig, key: str):
    """``cfg``'s value for ``key``, or what a configuration without it ran with (:data:`ABSENT_KEYS`)."""
    return OmegaConf.select(cfg, key, default=ABSENT_KEYS[key])
