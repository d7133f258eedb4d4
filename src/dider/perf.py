"""Process-level performance settings.

On Linux/glibc every tensor above the mmap threshold (128 KiB to 32 MiB, adaptive) is a fresh mmap
whose pages fault in on first touch and are unmapped on free. Training allocates and frees
tens-of-MiB activations many times per step, so page faults take a large share of a CPU training
step. Raising the thresholds lets glibc keep and reuse that memory, but only up to 32 MiB, glibc's
largest threshold: the recurrent step's 100-200 MiB edge tensors would still come fresh from mmap
every time. ``heap`` serves every size from the heap. The measurements: ``docs/performance.md``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

import torch

_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -2, -3, -4
# heap: thresholds raised and no mmap at all, every freed block reused (faster steps where tensors
# exceed 32 MiB, for a higher peak: a heap is never returned; docs/performance.md); thresholds: the
# thresholds only; system: glibc's own settings.
ALLOCATORS = ("heap", "thresholds", "system")
_applied: str | None = None


def allocator_mode(mode: str | None = None) -> str:
    """The allocator setting a process takes: ``mode``, else ``$DIDER_ALLOCATOR``, else ``heap``;
    ``DIDER_NO_MALLOPT=1`` means ``system`` whatever was asked."""
    return ("system" if os.environ.get("DIDER_NO_MALLOPT")
            else mode or os.environ.get("DIDER_ALLOCATOR") or "heap")


def tune_allocator(mode: str | None = None) -> bool:
    """Keep freed memory for reuse (glibc only; a no-op elsewhere). ``mode``: one of
    :data:`ALLOCATORS`, resolved by :func:`allocator_mode`. Settings only grow more permissive
    within a process: glibc applies them to later allocations. -> whether applied."""
    global _applied
    mode = allocator_mode(mode)
    if mode not in ALLOCATORS:
        raise ValueError(f"allocator={mode!r}: expected one of {list(ALLOCATORS)}")
    if mode == "system" or not sys.platform.startswith("linux"):
        return False
    if _applied in (mode, "heap"):
        return True
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        ok = all([
            libc.mallopt(_M_MMAP_THRESHOLD, 32 * 2**20),  # glibc's maximum
            libc.mallopt(_M_TRIM_THRESHOLD, 2**30),
            libc.mallopt(_M_TOP_PAD, 256 * 2**20),
            *([libc.mallopt(_M_MMAP_MAX, 0)] if mode == "heap" else []),
        ])  # fmt: skip
    except (OSError, AttributeError):
        return False
    _applied = mode if ok else None
    return ok


def native_bf16(device: str = "cpu") -> bool:
    """Whether ``device`` computes in bf16 natively. A CPU without AVX-512 (oneDNN's test) emulates
    bf16 autocast, far slower than fp32 (``docs/journal/performance_history.md``)."""
    if device.startswith("cuda"):
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())


def compile_modules(model: torch.nn.Module) -> None:
    """``torch.compile`` a RelationalVAE's hot plugins in place: the encoder and decoder (the GNN
    and its element-wise chains). The segment logic stays eager: its slot boundaries change every
    step. Shapes are static at first and marked dynamic when they change (real data: the agent count
    varies per batch)."""
    for name in ("encoder", "decoder"):
        getattr(model, name).compile()


def trains_on_cpu(accelerator: str | None) -> bool:
    """Whether a trainer with ``trainer.accelerator=accelerator`` runs on the CPU."""
    return accelerator == "cpu" or (accelerator in (None, "auto") and not torch.cuda.is_available())
