"""Counting where a step makes the host wait for the device: a dispatch mode that records every op
that reads a value back (``aten._local_scalar_dense``: ``.item()``, ``bool(tensor)``,
``int(tensor)``) or whose output shape depends on the values (``nonzero``, boolean indexing, ...),
by the dider source line that called it. On a CPU nothing waits, but the same ops are the ones that
stall a GPU's stream and that a CUDA graph cannot hold, so a CPU can count them."""

from __future__ import annotations

import collections
import traceback
from typing import Any

import torch
from torch.utils._python_dispatch import TorchDispatchMode

# ops that make the host wait: a value read back, an output shape only the values decide, or a
# tensor made from Python data (``torch.tensor(...)``, ``t[i] = 1``: on a GPU a copy from pageable
# host memory, which a CUDA graph cannot hold)
WAITS = frozenset({"_local_scalar_dense", "lift_fresh", "nonzero", "masked_select", "_unique2",
                   "unique_dim", "unique_consecutive", "repeat_interleave", "masked_scatter"})


class HostSyncs(TorchDispatchMode):
    """``with HostSyncs() as syncs: ...`` -> ``syncs.where``: a Counter of "op at file:line" (the
    innermost dider frame; "op" alone for ops outside the package), ``syncs.total``."""

    def __init__(self) -> None:
        super().__init__()
        self.where: collections.Counter[str] = collections.Counter()

    @property
    def total(self) -> int:
        return sum(self.where.values())

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (),
                           kwargs: dict | None = None) -> Any:
        name = func.__name__.split(".")[0]
        indices = (args[1] if name in ("index", "index_put", "index_put_") and len(args) > 1
                   else None)
        boolean_index = isinstance(indices, (list, tuple)) and any(
            isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in indices)
        if name in WAITS or boolean_index:
            frames = [f for f in traceback.extract_stack()
                      if "/dider/" in f.filename and not f.filename.endswith("bench/syncs.py")]
            where = (f"{frames[-1].filename.split('/dider/')[-1]}:{frames[-1].lineno}" if frames
                     else "outside dider")
            self.where[f"{name} at {where}"] += 1
        return func(*args, **(kwargs or {}))
