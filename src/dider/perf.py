"""Process-level performance settings.

On Linux/glibc every tensor above the mmap threshold (128 KiB to 32 MiB, adaptive) is a fresh
mmap whose pages fault in on first touch and are unmapped on free. Training allocates and frees
tens-of-MiB activations many times per step, so on the 2-core CPU a third of a DNRI step went to
page faults (measured: 3.5 s -> 2.4 s per synthetic step of batch 128 with the settings below).
Raising the thresholds lets glibc keep and reuse that memory.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

import torch

_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
_applied = False


def tune_allocator() -> bool:
    """Keep freed heap memory for reuse (glibc only; a no-op elsewhere or with DIDER_NO_MALLOPT=1)."""
    global _applied
    if _applied or not sys.platform.startswith("linux") or os.environ.get("DIDER_NO_MALLOPT"):
        return _applied
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        ok = all([
            libc.mallopt(_M_MMAP_THRESHOLD, 32 * 2**20),  # glibc's maximum
            libc.mallopt(_M_TRIM_THRESHOLD, 2**30),
            libc.mallopt(_M_TOP_PAD, 256 * 2**20),
        ])  # fmt: skip
    except (OSError, AttributeError):
        return False
    _applied = bool(ok)
    return _applied


def native_bf16(device: str = "cpu") -> bool:
    """Whether ``device`` computes in bf16 natively. A CPU without AVX-512 (oneDNN's test) emulates bf16
    autocast: on a 2-core AVX2 CPU a synthetic DNRI training step took 54.7 s in bf16 against 2.7 s in fp32."""
    if device.startswith("cuda"):
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())


def compile_modules(model: torch.nn.Module) -> None:
    """``torch.compile`` a RelationalVAE's hot plugins in place: the encoder and decoder (the GNN and its
    element-wise chains). The segment logic stays eager: its slot boundaries change every step. Shapes are
    static at first and marked dynamic when they change (real data: the agent count varies per batch)."""
    for name in ("encoder", "decoder"):
        getattr(model, name).compile()
