"""torchrl-reset: reset agents that learn from examples of initial states, as TorchRL components.

Implements Kim et al., "Automating Reinforcement Learning with Example-based Resets" (RA-L 2022).
"""
from .collector import DualCollector
from .collector_env import find_trigger_transforms
from .ensemble import (EnsembleValueOperator, prior_bias_bound, reduce_members, success_classifier, success_probability,
                       with_prior)
from .example_buffer import InitialStateBuffer
from .nstep import EpisodeWindowSampler, NStepStateTransform
from .rce_loss import RCELoss, actor_loss, classifier_loss, label_weight, rce_label, shared_label
from .trigger import ResetTriggerTransform
from . import accel  # the accelerator: the same numbers, faster (torchrl_reset.accel)

__version__ = "0.1.0"

__all__ = [
    "accel",
    "DualCollector",
    "EnsembleValueOperator",
    "EpisodeWindowSampler",
    "InitialStateBuffer",
    "NStepStateTransform",
    "RCELoss",
    "ResetTriggerTransform",
    "actor_loss",
    "classifier_loss",
    "label_weight",
    "prior_bias_bound",
    "rce_label",
    "shared_label",
    "with_prior",
    "find_trigger_transforms",
    "reduce_members",
    "success_classifier",
    "success_probability",
]
