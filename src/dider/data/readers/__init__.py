"""Readers of trajectory formats and sources of clips.

A track reader turns its files into one long track table, a DataFrame with the columns agent, frame (integer steps),
x, y and optionally scene, vx, vy and agent_class, naming the file and line of any problem; ``data=table``'s
windows, split and normaliser then take it (:func:`dider.data.table_reading.read_table`). A new format is one reader
here, entered in ``READERS``, and one YAML in ``conf/data`` that names it (``data.reader``). ``kloppy`` reads a
soccer provider's files into the same rows (``data=soccer``).

A clip source gives each split as :class:`~dider.data.tracks.Clips`, already cut to a fixed length, raw: the
simulators (``push``, ``particles``) and the files that ship clips (``nri_files``, ``dnri_files``, ``basketball``,
``trajectories``); its data module splits, caps and normalises them (:mod:`dider.data.clip_splits`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pandas as pd

from dider.data.readers import eth_ucy

READERS: dict[str, Callable[[Path], pd.DataFrame]] = {"eth_ucy": eth_ucy.read}
COLUMNS = ("scene", "agent", "frame", "x", "y", "vx", "vy", "agent_class")


def read_tracks(reader: str, path: Path) -> pd.DataFrame:
    """The track table of ``path`` by the reader named ``reader`` (a key of :data:`READERS`)."""
    if reader not in READERS:
        raise ValueError(f"data.reader={reader!r}: unknown; known: table (data.columns over a .csv or .parquet), "
                         f"{', '.join(sorted(READERS))}")
    if not path.exists():
        raise FileNotFoundError(f"data.path={path}: no such file or folder")
    df = READERS[reader](path)
    if missing := [k for k in ("agent", "frame", "x", "y") if k not in df.columns]:
        raise ValueError(f"data.reader={reader}: its table lacks the column(s) {missing}")
    if len(df) == 0:
        raise ValueError(f"{path}: no rows (expected one row per agent per frame)")
    return df[[k for k in COLUMNS if k in df.columns]]
