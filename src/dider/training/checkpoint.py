"""Atomic checkpoint files: a run killed while saving never leaves a truncated ``last.ckpt`` behind.

Lightning's ``ModelCheckpoint`` hands every save to the trainer's ``CheckpointIO``. Its default
writes through an fsspec transaction whose temporary file lives in the system temp folder, so the
final move can be a cross-device copy that a kill interrupts. :class:`AtomicCheckpointIO` writes to
a temporary file in the destination folder, fsyncs it and ``os.replace``-s it over the target
(atomic on POSIX and Windows), then fsyncs the folder. Its loads go through dider's one checkpoint
reader (:func:`dider.models.checkpoint_format.read`). ``dider.run`` installs it on every trainer it
builds.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.fabric.utilities.types import _PATH

from dider.io import atomic_torch_save
from dider.models.checkpoint_format import read


class AtomicCheckpointIO(TorchCheckpointIO):
    """``TorchCheckpointIO`` whose local saves are atomic (remote URLs keep Lightning's own
    handling)."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: _PATH,
                        storage_options: Any | None = None) -> None:
        if storage_options is not None or "://" in str(path):
            super().save_checkpoint(checkpoint, path, storage_options)
            return
        atomic_torch_save(checkpoint, Path(path))

    def load_checkpoint(self, path: _PATH, map_location: Any = None,
                        weights_only: bool | None = None
                        ) -> dict[str, Any]:
        """A resumed or tested run's checkpoint through dider's one reader (``weights_only``,
        today's format, a refusal naming the file); remote URLs keep Lightning's own handling."""
        if "://" in str(path):
            return super().load_checkpoint(path, map_location, weights_only)
        return read(path)
