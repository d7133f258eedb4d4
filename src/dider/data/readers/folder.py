"""The folder a file reader reads (``data.source.root``), checked before anything is read."""

from __future__ import annotations

from pathlib import Path


def data_root(root: str | Path | None, holding: str) -> Path:
    """``root`` as an existing folder; unset or missing raises naming ``data.source.root`` (``holding``: what it
    holds)."""
    if not root:
        raise ValueError(f"data.source.root is not set: point it at {holding}")
    folder = Path(root).expanduser()
    if not folder.is_dir():
        raise FileNotFoundError(f"data.source.root={folder}: no such folder")
    return folder
