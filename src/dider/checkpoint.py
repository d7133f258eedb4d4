"""Atomic checkpoint files: a run killed while saving never leaves a truncated ``last.ckpt`` behind.

Lightning's ``ModelCheckpoint`` hands every save to the trainer's ``CheckpointIO``. Its default writes
through an fsspec transaction whose temporary file lives in the system temp folder, so the final move can
be a cross-device copy that a kill interrupts. :class:`AtomicCheckpointIO` writes to a temporary file in
the destination folder, fsyncs it and ``os.replace``-s it over the target (atomic on POSIX and Windows),
then fsyncs the folder. ``dider.run`` installs it on every trainer it builds.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.fabric.utilities.types import _PATH


class AtomicCheckpointIO(TorchCheckpointIO):
    """``TorchCheckpointIO`` whose local saves are atomic (remote URLs keep Lightning's own handling)."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: _PATH, storage_options: Any | None = None) -> None:
        if storage_options is not None or "://" in str(path):
            super().save_checkpoint(checkpoint, path, storage_options)
            return
        atomic_save(checkpoint, Path(path))


def atomic_save(obj: Any, path: Path) -> None:
    """torch.save ``obj`` to ``path`` through a temporary file in the same folder and ``os.replace``.

    Readers see the old file or the complete new one, never a partial one; on any error (or a
    KeyboardInterrupt) the temporary file is removed.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)  # as an ordinary open() would create it (mkstemp makes it 0600)
        with os.fdopen(fd, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def _fsync_dir(folder: Path) -> None:
    """Make the rename durable (POSIX); a no-op where folders cannot be opened (Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
