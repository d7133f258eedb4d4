"""Atomic file writing: a killed process never leaves a half-written file behind; and the one reader
of a run's record (``metrics.json``), which names the file when it is not one.

Every writer goes through :func:`atomic_write`: the content goes to a temporary file in the target's
folder, which is flushed to disk and then renamed over the target, so readers (a cache lookup, a
resumed run, a report) see either the old file or the complete new one.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import torch


def atomic_write(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Call ``write(file)`` on a temporary file in ``path``'s folder, fsync it, rename it over
    ``path`` and fsync the folder. Readers see the old file or the complete new one, never a partial
    one; on any error (or a KeyboardInterrupt) the temporary file is removed. The file gets the
    permissions an ordinary ``open()`` would give it (mkstemp makes it 0600)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    # torch.save reports a full disk as "inline_container ... unexpected pos"
    except (OSError, RuntimeError) as e:
        Path(tmp).unlink(missing_ok=True)
        raise OSError(f"{path}: could not be written ({type(e).__name__}: "
                      f"{str(e).splitlines()[0] if str(e) else ''}); {_space(path.parent)}") from e
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def _space(folder: Path) -> str:
    """What usually stops a write: the free space and whether the folder is writable."""
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return "is the folder there and writable?"
    writable = "writable" if os.access(folder, os.W_OK) else "NOT writable"
    return f"{free / 2**20:.0f} MiB free on its disk, folder {writable}"


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


def atomic_write_bytes(path: Path, data: bytes) -> None:
    atomic_write(path, lambda f: f.write(data))


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def atomic_torch_save(obj: Any, path: Path) -> None:
    atomic_write(path, lambda f: torch.save(obj, f))


def read_run_record(path: Path) -> dict[str, Any]:
    """A run's ``metrics.json`` as a dict; ValueError naming ``path`` for one that is not JSON
    (half-written, or another file) or not a run's record (a JSON object with a ``metrics``
    object)."""
    try:
        record = json.loads(Path(path).read_text())
    except ValueError as e:
        raise ValueError(f"{path}: not JSON (half-written, or not a run's record): {e}") from None
    if not isinstance(record, dict) or not isinstance(record.get("metrics"), dict):
        raise ValueError(f"{path}: not a run's record (a JSON object with a 'metrics' object)")
    return record
