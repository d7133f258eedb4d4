"""Older data configs read as today's: a run folder's saved config (``.hydra/config.yaml``) written by an earlier
version, for the tools that rebuild its data module (``dider.analysis.diagnose``)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields
from typing import Any

from dider.data.loader import Loader

# The forecast protocol's keys, which data configs once carried beside the model (today the model's alone).
PROTOCOL_KEYS = ("burn_in", "horizons", "burn_in_mode")


def upgrade_data_node(data: Mapping[str, Any]) -> dict[str, Any]:
    """A data config (plain) in today's layout: the loader's settings in its ``loader`` node where an older config
    has them at the top (``batch_size``, ``eval_batch_size``, ``num_workers``, ``pin_memory``), and without the
    forecast protocol's keys (``burn_in``, ``horizons``, ``burn_in_mode``: the model's)."""
    names = [f.name for f in fields(Loader)]
    node = {k: v for k, v in data.items() if k not in names and k not in PROTOCOL_KEYS}
    if older := {k: data[k] for k in names if k in data}:
        node["loader"] = {**older, **dict(data.get("loader") or {})}
    return node
