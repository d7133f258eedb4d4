"""What a checkpoint records of the data a model was trained on (``checkpoint["dider"]["data"]``): the data module's
class and its arguments, nested as its config nests them, the feature layout, its state (the normaliser) and the
input frames per step. A trained model reads new data by it (:mod:`dider.trained`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import lightning as L

from dider.data.common import FEATURES


def data_description(dm: L.LightningDataModule | None) -> dict[str, object]:
    """What a checkpoint records of the data it was trained on: the data module's class and arguments (nested as
    its config nests them: ``source``, ``windows``, ``loader``), the feature layout, its ``state_dict`` (the
    normaliser) and the input frames per step; {} without one."""
    if dm is None:
        return {}
    cls = type(dm)
    return {"target": f"{cls.__module__}.{cls.__qualname__}", "args": _recorded(dict(getattr(dm, "hparams", {}))),
            "features": list(FEATURES), "frame_step": int(getattr(dm, "frame_step", 1)), "state": dm.state_dict()}


RECORDED = (int, float, str, bool, type(None))


def _recorded(node: Mapping[str, Any]) -> dict[str, Any]:
    """The plain part of a data module's arguments, as a checkpoint keeps it (read back with ``weights_only``):
    mappings as dicts, sequences as lists, numbers, strings and None; anything else (an object a user passed in
    place of a setting) is left out."""
    def keep(value: Any) -> bool:
        return isinstance(value, (Mapping, list, tuple, *RECORDED))

    def copy(value: Any) -> Any:
        if isinstance(value, Mapping):
            return {str(k): copy(v) for k, v in value.items() if keep(v)}
        if isinstance(value, (list, tuple)):
            return [copy(v) for v in value if keep(v)]
        return value
    return copy(node)
