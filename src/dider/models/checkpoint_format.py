"""What a dider checkpoint holds and its format number, checked where a checkpoint is read.

Every checkpoint dider writes records ``checkpoint["dider"]["format"]`` (:data:`FORMAT`): ``net`` in
the hyper-parameters (the network's config, every plugin's settings as its constructor names them),
the LightningModule's settings beside it, the network's weights under ``model.`` in the state dict,
and under ``dider.data`` the data module's class and arguments nested as its config nests them
(``source``, ``windows``, ``loader``), its normaliser and the feature layout. Where a checkpoint is
read (``dider.load``, ``mode=eval`` / ``predict``, a resumed run,
``RelationalVAEModule.load_from_checkpoint``, ``RelationalVAE``'s readers), :func:`check_format`
refuses any other format by name: there is no reading of the layout that development versions before
0.2.0 wrote (format 1, no number; format 2, the data arguments flat; format 3, the data source by
its reader's name); a model built from a config never passes through it.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

FORMAT = 4


def format_of(checkpoint: Mapping[str, Any]) -> int:
    """The format a checkpoint was written in (1: before the number existed)."""
    return int((checkpoint.get("dider") or {}).get("format", 1))


def stamp(checkpoint: dict[str, Any], **fields: Any) -> None:
    """Mark a checkpoint being written as today's format, with what else dider keeps in it
    (``fields``)."""
    checkpoint["dider"] = {"format": FORMAT, **fields}


def check_format(checkpoint: dict[str, Any], where: str | Path = "checkpoint") -> dict[str, Any]:
    """The checkpoint (a loaded dict) if it is of today's format; any other format is refused,
    naming ``where`` and what reads it."""
    marks = checkpoint.get("dider") or {}
    if not isinstance(marks, Mapping) or type(marks.get("format", 1)) is not int:
        raise ValueError(f"{where}: not a dider checkpoint (its format mark dider.format="
                         f"{(marks.get('format') if isinstance(marks, Mapping) else marks)!r} is "
                         "no whole number)")
    found = format_of(checkpoint)
    if found != FORMAT:
        by = "a newer dider: upgrade the package" if found > FORMAT else (
            "a development version before 0.2.0: retrain it with this version (no reading of that "
            "layout ships)")
        raise ValueError(f"{where}: written in checkpoint format {found} by {by}; this version "
                         f"reads format {FORMAT}")
    return checkpoint


def read(path: str | Path, where: str | None = None, **load: Any) -> dict[str, Any]:
    """The one reader of a checkpoint file: loaded with ``weights_only`` (tensors and plain values:
    a planted pickle cannot run), a training checkpoint (``state_dict`` and ``hyper_parameters``) of
    today's format, else a ValueError naming it (``where``: how messages name it; default the path).
    ``load``: more of torch.load's arguments (``mmap``)."""
    where = where or str(path)
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True, **load)
    except Exception as e:  # torch raises many types for a foreign or damaged file
        raise ValueError(
            f"{where}: not a readable dider checkpoint ({type(e).__name__}: {e})") from e
    if (not isinstance(checkpoint, dict) or "state_dict" not in checkpoint
        or "hyper_parameters" not in checkpoint):
        raise ValueError(f"{where}: not a dider training checkpoint (no state_dict / "
                         "hyper_parameters)")
    return check_format(checkpoint, where)


def network_config(node: Mapping[str, Any]) -> dict[str, Any]:
    """The network's config of a model config (``cfg.model``: its ``net`` node) or the network's
    config itself."""
    return dict(node["net"]) if "net" in node else dict(node)
