"""Parameter-keyed on-disk caches: a file name carries a hash of everything that made its content, files are
written atomically (:mod:`dider.io`), so a killed process never leaves a half-written one, and read with
``weights_only`` (tensors and plain values: a planted file cannot run code)."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch

from dider.io import atomic_torch_save

log = logging.getLogger(__name__)


def cache_key(params: dict[str, Any]) -> str:
    """A short stable hash of JSON-serialisable parameters."""
    blob = json.dumps(params, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def load_or_build(path: Path, build: Callable[[], Any]) -> Any:
    """The cache at ``path``, or ``build()``'s result written there atomically.

    A cache that cannot be read (damaged, truncated, or a planted pickle that ``weights_only`` refuses) is
    named in a warning, moved aside to ``<name>.corrupt`` and rebuilt, so one bad file never breaks every
    later run. Temporary files that killed writers left in the folder (older than an hour) are removed.
    """
    remove_stale_temporaries(path.parent)
    if path.exists():
        try:
            return torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # torch raises many types for a bad file; any of them means: rebuild
            aside = path.with_name(path.name + ".corrupt")
            log.warning("cache %s cannot be read (%s: %s): moved to %s, rebuilding", path, type(e).__name__,
                        str(e).splitlines()[0] if str(e) else "", aside)
            os.replace(path, aside)
    blob = build()
    atomic_torch_save(blob, path)
    return blob


def cached_splits(sizes: Mapping[str, int], path_of: Callable[[str, int], Path],
                  build: Callable[[str, int, Path], Any]) -> dict[str, Any]:
    """Each split of ``sizes`` (split -> number of clips) from its cache file ``path_of(split, size)``, or
    ``build(split, size, path)``'s result written there (a generated data set's splits)."""
    out = {}
    for split, size in sizes.items():
        path = path_of(split, size)
        out[split] = load_or_build(path, lambda split=split, size=size, path=path: build(split, size, path))
    return out


def remove_stale_temporaries(folder: Path, older_than_s: float = 3600.0) -> None:
    """Delete ``.<name>.*.tmp`` files of atomic writers killed before their rename (a live writer's file is
    younger than ``older_than_s``)."""
    if not folder.is_dir():
        return
    now = time.time()
    for tmp in folder.glob(".*.tmp"):
        try:
            if now - tmp.stat().st_mtime > older_than_s:
                tmp.unlink()
                log.info("removed %s, left by a killed writer", tmp)
        except OSError:  # another process removed it first
            pass
