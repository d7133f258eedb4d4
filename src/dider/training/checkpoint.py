"""Atomic checkpoint files: a run killed while saving never leaves a truncated ``last.ckpt`` behind.

Lightning's ``ModelCheckpoint`` hands every save to the trainer's ``CheckpointIO``. Its default writes
through an fsspec transaction whose temporary file lives in the system temp folder, so the final move can
be a cross-device copy that a kill interrupts. :class:`AtomicCheckpointIO` writes to a temporary file in
the destination folder, fsyncs it and ``os.replace``-s it over the target (atomic on POSIX and Windows),
then fsyncs the folder. ``dider.run`` installs it on every trainer it builds.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.fabric.utilities.types import _PATH

from dider.io import atomic_torch_save


class AtomicCheckpointIO(TorchCheckpointIO):
    """``TorchCheckpointIO`` whose local saves are atomic (remote URLs keep Lightning's own handling)."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: _PATH, storage_options: Any | None = None) -> None:
        if storage_options is not None or "://" in str(path):
            super().save_checkpoint(checkpoint, path, storage_options)
            return
        atomic_torch_save(checkpoint, Path(path))
