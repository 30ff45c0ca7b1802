"""The accelerator: everything in torchrl-reset that exists for speed alone, in one place.

The library's plain classes (:class:`~torchrl_reset.EnsembleValueOperator`,
:class:`~torchrl_reset.RCELoss`, torchrl's ``DDPGLoss`` and ``SoftUpdate``) are the specification
(the DDPG agents use torchrl's ``DDPGLoss`` on either path):
they read like the paper's equations. The classes here compute the same numbers faster, each a
drop-in subclass or replacement with the same parameters, keys and state dicts:

=================================  ===============================================================
:class:`FastEnsembleValueOperator`  fused, thread-balanced member products; trained and prior members
                                    as one stack without gradients; a shared state part for the
                                    loss's pairs; the success examples' prior part kept
:class:`FastRCELoss`                one actor pass and one target pass per update; uses the above
:class:`FusedSoftUpdate`            torchrl's ``SoftUpdate`` as one ``_foreach_lerp_``
:class:`TensorModule`               one tensor in, one out, without tensordict's output conversion
:func:`retain_freed_memory`         glibc keeps freed memory (no page faults on big temporaries)
:func:`choose_matmul_precision`     the CPU float32 product path (plain or oneDNN with bf16 inside)
=================================  ===============================================================

:func:`components` is the switch: ``components(True)`` gives the fast classes, ``components(False)``
the plain ones; the recipes call it with ``speed.accelerate`` (true by default).
``tests/test_accel.py`` runs both on the same inputs and pins them together.
"""
from __future__ import annotations

from dataclasses import dataclass

from tensordict.nn import TensorDictModule
from torchrl.objectives import DDPGLoss, SoftUpdate

from ..ensemble import EnsembleValueOperator
from ..rce_loss import RCELoss
from .cpu import MATMUL_PRECISIONS, choose_matmul_precision, matmul_products, retain_freed_memory
from .ensemble import FastEnsembleValueOperator
from .modules import FusedSoftUpdate, TensorModule
from .rce import FastRCELoss

__all__ = [
    "Components",
    "components",
    "FastEnsembleValueOperator",
    "FastRCELoss",
    "FusedSoftUpdate",
    "TensorModule",
    "MATMUL_PRECISIONS",
    "choose_matmul_precision",
    "matmul_products",
    "retain_freed_memory",
]


@dataclass(frozen=True)
class Components:
    """The classes an agent is built from: plain (the reference) or fast (the accelerator)."""

    ensemble: type
    rce_loss: type
    ddpg_loss: type
    soft_update: type
    accelerated: bool

    def tensor_module(self, module, in_key: str, out_key: str):
        """``tensordict[out_key] = module(tensordict[in_key])``."""
        if self.accelerated:
            return TensorModule(module, in_key, out_key)
        return TensorDictModule(module, in_keys=[in_key], out_keys=[out_key])


def components(accelerate: bool = True) -> Components:
    """The fast classes (``accelerate=True``) or the plain reference ones (``False``).

    Examples:
        >>> from torchrl_reset import accel
        >>> accel.components(False).rce_loss.__name__, accel.components(True).rce_loss.__name__
        ('RCELoss', 'FastRCELoss')
    """
    if accelerate:
        return Components(FastEnsembleValueOperator, FastRCELoss, DDPGLoss, FusedSoftUpdate, True)
    return Components(EnsembleValueOperator, RCELoss, DDPGLoss, SoftUpdate, False)
