"""CPU settings for speed (the recipes' ``speed.*``): freed memory kept in the process, and how the
updates' float32 matrix products run."""
from __future__ import annotations

import ctypes
import sys
from contextlib import contextmanager

import torch

__all__ = ["retain_freed_memory", "MATMUL_PRECISIONS", "choose_matmul_precision", "matmul_products"]


def retain_freed_memory() -> bool:
    """Keep memory freed by the process instead of handing it back to the system (glibc only).

    An update allocates tens of MB of temporaries; by default glibc returns big blocks to the
    system on free and every new allocation then page-faults on first touch (about 1000 faults,
    1.5 ms per reset update measured on 2 cores). Returns whether the setting was applied.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        return bool(libc.mallopt(m_mmap_threshold, 1 << 30)) and bool(libc.mallopt(m_trim_threshold, 1 << 30))
    except (OSError, AttributeError):  # not glibc
        return False


MATMUL_PRECISIONS = ("auto", "ieee", "bf16")


def _product_error(a: torch.Tensor, b: torch.Tensor, exact: torch.Tensor) -> float:
    return float(((a @ b).double() - exact).abs().max() / exact.abs().max())


def choose_matmul_precision(setting: str) -> str:
    """How the updates' float32 matrix products run on CPU: ``ieee`` or ``bf16`` (see :func:`matmul_products`).

    ``ieee``: plain float32 products. ``bf16``: torch's ``torch.backends.mkldnn.matmul.fp32_precision
    = "bf16"``, which hands float32 products to oneDNN and lets it use bf16 arithmetic inside. On
    the 2-core AVX512-BF16 machines this project is measured on, that path is about 2x faster on the
    reset update's products and as accurate as plain float32 (a reset update's losses and gradients
    agree with float64 to about 1e-7 either way), but other processors may use plain bf16 there
    (about 3 significant digits). ``auto`` therefore measures it: one 256 x 400 x 300 product
    against float64, and ``bf16`` only when its error stays within 4x that of plain float32.
    Leaves the process's setting as it found it.
    """
    if setting not in MATMUL_PRECISIONS:
        raise ValueError(f"matmul precision must be one of {MATMUL_PRECISIONS}, got {setting!r}.")
    if setting == "ieee" or not torch.backends.mkldnn.is_available():
        return "ieee"
    if setting == "bf16":
        return "bf16"
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(256, 400, generator=gen) * 2 - 1
    b = torch.rand(400, 300, generator=gen) * 2 - 1
    exact = a.double() @ b.double()
    with matmul_products("bf16"):
        fast = _product_error(a, b, exact)
    with matmul_products("ieee"):
        plain = _product_error(a, b, exact)
    return "bf16" if fast <= 4 * max(plain, 1e-7) else "ieee"


@contextmanager
def matmul_products(precision: str):
    """Runs the block with CPU float32 products in ``precision`` (``ieee`` or ``bf16``), then restores.

    The recipe uses it around each update only: for the one-row products of acting (policy and
    trigger, every step) oneDNN's path costs more per call (about 29 instead of 10 microseconds for
    a 400 x 300 layer on one row), while for the updates' batches it is about 2x faster.
    """
    backend = torch.backends.mkldnn.matmul
    previous = backend.fp32_precision
    backend.fp32_precision = precision
    try:
        yield
    finally:
        backend.fp32_precision = previous
