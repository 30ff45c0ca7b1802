"""Many runs in one process, and one agent pair over many copies of a task: an option, fenced off.

The paper's pieces (the rest of :mod:`torchrl_reset`) run one agent pair on one environment. This
subpackage runs S independent runs in one process, each run's agents updated by one batched call
(:class:`RunRCEUpdate`, :class:`RunDDPGUpdate`, over :class:`RunEnsembles` and :class:`RunPolicies`
with :class:`RunMaskedAdam` and :class:`RunMaskedSoftUpdate`), and acts in N copies of a task at once,
each copy in its own phase (:class:`BatchedDualCollector`, with the trigger row by row:
:class:`RowResetTriggerTransform`). The recipe uses it for ``seeds=`` and
``arms=`` (docs/many-runs.md). It computes what the single-run classes compute, run by run, from the
same equations (:func:`~torchrl_reset.rce_loss.shared_label`, :func:`~torchrl_reset.rce_loss.classifier_loss`,
:func:`~torchrl_reset.rce_loss.actor_loss`, :func:`~torchrl_reset.ensemble.with_prior`); the tests pin
each to the single run. :class:`RunPolicies` batches policies of one layout: a ReLU MLP ending in
torchrl's ``TanhModule``.
"""
from .agents import RunDDPGUpdate, RunEnsembles, RunPolicies, RunRCEUpdate, bind_runs
from .collector import BatchedDualCollector, CopyView, PooledCollector, split_phases
from .optim import RunMaskedAdam, RunMaskedSoftUpdate
from .trigger import RowResetTriggerTransform

__all__ = [
    "BatchedDualCollector",
    "CopyView",
    "PooledCollector",
    "RunDDPGUpdate",
    "RunEnsembles",
    "RunMaskedAdam",
    "RunMaskedSoftUpdate",
    "RunPolicies",
    "RunRCEUpdate",
    "RowResetTriggerTransform",
    "bind_runs",
    "split_phases",
]
