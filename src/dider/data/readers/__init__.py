"""Readers of trajectory formats and sources of clips.

A track reader turns its files into one long track table, a DataFrame with the columns agent, frame (integer steps),
x, y and optionally scene, vx, vy and agent_class, naming the file and line of any problem; ``data=table``'s
windows, split and normaliser then take it (:func:`dider.data.table_reading.read_table`). A new format is one module
here that says ``TRACKS = True`` and defines ``read(path) -> DataFrame``, found by its name (``data.source.reader``: the
module's), and one YAML in ``conf/data`` that names it. ``kloppy`` reads a soccer provider's files into the same rows
(``data=soccer``).

A clip source gives its clips already cut to a fixed length, raw (:class:`~dider.data.clip_source.Clips`): the
simulators (``push``, ``particles``) and the files that ship clips (``nri_files``, ``dnri_files``, ``basketball``,
``trajectories``). Its module names its settings class ``CLIPS``: a frozen dataclass (the ``data.source`` node) with
the members of :class:`~dider.data.clip_source.ClipSource` (``reader``, the module's name; ``clips(sizes, cache_dir)``,
the splits the input holds; ``where()``; and the optional ones). :class:`~dider.data.clips.ClipsDataModule` splits,
caps and normalises them.
"""

from __future__ import annotations

import importlib
import pkgutil
from functools import cache
from pathlib import Path
from types import ModuleType

import pandas as pd

COLUMNS = ("scene", "agent", "frame", "x", "y", "vx", "vy", "agent_class")


@cache
def _modules() -> dict[str, ModuleType]:
    return {info.name: importlib.import_module(f"{__name__}.{info.name}") for info in pkgutil.iter_modules(__path__)}


def track_readers() -> dict[str, ModuleType]:
    """The track readers of this package by name: its modules that say ``TRACKS = True``."""
    return {name: module for name, module in _modules().items() if getattr(module, "TRACKS", False)}


def clip_sources() -> dict[str, type]:
    """The clip sources of this package by reader name: the settings class each module names ``CLIPS``."""
    return {name: module.CLIPS for name, module in _modules().items() if hasattr(module, "CLIPS")}


def reader_problem(reader: object, others: tuple[str, ...] = ()) -> str | None:
    """The setting rule of ``data.source.reader``: ``table``, a track reader's name or one of ``others`` (the
    sources with settings of their own)."""
    known = ["table", *sorted(track_readers()), *others]
    return None if isinstance(reader, str) and reader in known else f"expected one of {known}"


def read_tracks(reader: str, path: Path) -> pd.DataFrame:
    """The track table of ``path`` by the track reader named ``reader`` (:func:`track_readers`)."""
    if (module := track_readers().get(reader)) is None:
        raise ValueError(f"data.source.reader={reader!r}: unknown; known: table (data.source.columns over a .csv or "
                         f".parquet), "
                         f"{', '.join(sorted(track_readers()))}")
    if not path.exists():
        raise FileNotFoundError(f"data.source.path={path}: no such file or folder")
    df = module.read(path)
    if missing := [k for k in ("agent", "frame", "x", "y") if k not in df.columns]:
        raise ValueError(f"data.source.reader={reader}: its table lacks the column(s) {missing}")
    if len(df) == 0:
        raise ValueError(f"{path}: no rows (expected one row per agent per frame)")
    return df[[k for k in COLUMNS if k in df.columns]]
