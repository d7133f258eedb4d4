"""Reading a long-format trajectory table (``data=table``): one ``.csv`` or ``.parquet`` file, one row per agent
per frame, columns named in ``data.source.columns`` (:func:`read_table`), or the DataFrame a track format's class read
with the columns of :data:`TRACK_COLUMNS` (:func:`format_table`); every problem is named with the file, the column
and the CSV line (parquet: the row) before any windowing. :mod:`dider.data.table` cuts the result into windows.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from dider.data.columns import csv_header

log = logging.getLogger(__name__)

DEFAULT_COLUMNS: dict[str, str | None] = {"scene": None, "agent": "agent", "frame": "frame", "x": "x", "y": "y",
                                          "vx": None, "vy": None, "agent_class": None}
REQUIRED = ("agent", "frame", "x", "y")
TRACK_COLUMNS = ("scene", "agent", "frame", "x", "y", "vx", "vy", "agent_class")  # a format's DataFrame: these
NUMERIC = ("frame", "x", "y", "vx", "vy")
SUFFIXES = (".csv", ".parquet")


def columns_problem(columns: Any) -> str | None:
    """The rule of ``data.source.columns`` (the preflight's): a mapping whose entries :func:`check_columns` accepts."""
    if columns is not None and not isinstance(columns, Mapping):
        return (f"expected a mapping of key -> column name, e.g. {{agent: id, frame: t}} (keys: "
                f"{list(DEFAULT_COLUMNS)})")
    try:
        check_columns(columns)
    except ValueError as e:
        return str(e)
    return None


def check_columns(columns: Mapping[str, Any] | None) -> dict[str, str | None]:
    """``data.source.columns`` merged over the defaults; raises naming the key of an unknown, missing or clashing
    entry."""
    if columns is not None and not isinstance(columns, Mapping):
        raise ValueError(f"data.source.columns={columns!r}: {columns_problem(columns)}")
    given = dict(columns or {})
    if unknown := sorted(set(given) - set(DEFAULT_COLUMNS)):
        raise ValueError(f"data.source.columns: unknown key(s) {unknown} (known: {list(DEFAULT_COLUMNS)})")
    cols = {**DEFAULT_COLUMNS, **given}
    for key, name in cols.items():
        if name is None and key in REQUIRED:
            raise ValueError(f"data.source.columns.{key} is null: the {key} column is required")
        if name is not None and not (isinstance(name, str) and name):
            raise ValueError(f"data.source.columns.{key}={name!r}: expected a column name or null")
    if (cols["vx"] is None) != (cols["vy"] is None):
        raise ValueError(f"data.source.columns: vx={cols['vx']!r}, vy={cols['vy']!r}: give both velocity columns or "
                         f"neither (null: finite differences)")
    named = [n for n in cols.values() if n is not None]
    if clash := sorted({n for n in named if named.count(n) > 1}):
        raise ValueError(f"data.source.columns: column(s) {clash} named for more than one key")
    return cols


# -- reading and validating


def _row(path: Path, i: int) -> str:
    """Where row i of the table is in the file: the CSV line (line 1 is the header) or the parquet row."""
    return f"line {i + 2}" if path.suffix.lower() == ".csv" else f"row {i}"


def _read_frame(path: Path, names: list[str], optional: Sequence[str] = ()) -> pd.DataFrame:
    """The named columns of the file, and those of ``optional`` it has (types inferred; checked by the
    callers)."""
    if path.suffix.lower() not in SUFFIXES:
        raise ValueError(f"data.source.path={path}: unknown extension {path.suffix!r}; expected one of "
                         f"{list(SUFFIXES)}")
    if not path.is_file():
        raise FileNotFoundError(f"data.source.path={path}: no such file")
    csv = path.suffix.lower() == ".csv"
    # CSV: the header first, so a missing column is named before the rows are read. Parquet: every column
    # (reading the schema alone needs engine-specific code).
    whole = None if csv else _read_parquet(path)
    found = csv_header(path) if whole is None else [str(c) for c in whole.columns]
    if missing := [n for n in names if n not in found]:
        raise ValueError(f"{path}: missing column(s) {missing} (found {found}); name them in data.source.columns")
    names = names + [n for n in optional if n in found and n not in names]
    try:
        df = pd.read_csv(path, usecols=names, low_memory=False) if whole is None else whole[names]
    except (ValueError, OSError, pd.errors.ParserError) as e:
        raise ValueError(f"{path}: not a readable table ({type(e).__name__}: {e})") from e
    if len(df) == 0:
        raise ValueError(f"{path}: no rows (expected one row per agent per frame)")
    return df


def _read_parquet(path: Path) -> pd.DataFrame:
    try:
        return pd.read_parquet(path)
    except ImportError as e:
        raise ImportError(f"data.source.path={path}: reading .parquet needs pyarrow (pip install pyarrow) or "
                          f"fastparquet; or save the table as .csv ({e})") from None
    except (ValueError, OSError) as e:
        raise ValueError(f"{path}: not a readable parquet file ({type(e).__name__}: {e})") from e


def _numbers(path: Path, s: pd.Series) -> np.ndarray:
    """A required numeric column -> [R] float64; words, empty cells, NaN and inf raise with the first line."""
    if pd.api.types.is_numeric_dtype(s) and not pd.api.types.is_bool_dtype(s):
        a = s.to_numpy(dtype=np.float64, na_value=np.nan)
    else:
        parsed = pd.to_numeric(s, errors="coerce")
        words = (parsed.isna() & s.notna()).to_numpy()
        if words.any():
            i = int(np.argmax(words))
            raise ValueError(f"{path}: column {s.name!r} has {int(words.sum())} non-numeric value(s) (first on "
                             f"{_row(path, i)}: {s.iloc[i]!r})")
        a = parsed.to_numpy(dtype=np.float64, na_value=np.nan)
    bad = ~np.isfinite(a)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"{path}: column {s.name!r} has {int(bad.sum())} empty, NaN or inf value(s) (first on "
                         f"{_row(path, i)}: {s.iloc[i]!r})")
    big = np.abs(a) > np.finfo(np.float32).max  # would become inf in the float32 windows
    if big.any():
        i = int(np.argmax(big))
        raise ValueError(f"{path}: column {s.name!r} has values beyond the float32 range (first on "
                         f"{_row(path, i)}: {float(a[i])!r})")
    return a


def _ids(path: Path, s: pd.Series, integers: bool = True) -> tuple[np.ndarray, list[str] | None]:
    """An id column -> ([R] int64 ids, None) when every id is an integer (and ``integers``), else ([R]
    codes into the sorted names, names)."""
    empty = s.isna().to_numpy()
    if empty.any():
        i = int(np.argmax(empty))
        raise ValueError(f"{path}: column {s.name!r} is empty on {_row(path, i)}")
    if integers:
        num = pd.to_numeric(s, errors="coerce").to_numpy(dtype=np.float64, na_value=np.nan)
        if np.isfinite(num).all() and (num == np.round(num)).all() and np.abs(num).max() < 2**53:
            return num.astype(np.int64), None
    codes, names = pd.factorize(s.astype(str), sort=True)
    return codes.astype(np.int64), [str(n) for n in names]


def read_table(path: Path, columns: Mapping[str, str | None]) -> dict[str, Any]:
    """Read and validate the ``.csv`` or ``.parquet`` table ``path`` whose columns ``columns`` names
    (:func:`check_columns`' result): :func:`table_rows`."""
    named = {k: v for k, v in columns.items() if v is not None}
    # A column called "scene" is the scene id unless data.source.columns names one (or uses "scene" for another key).
    auto_scene = "scene" not in named and "scene" not in named.values()
    df = _read_frame(path, list(named.values()), optional=["scene"] if auto_scene else [])
    if auto_scene and "scene" in df.columns:
        named["scene"] = "scene"
        log.info("%s: column 'scene' read as the scene id (data.source.columns.scene is null); to read the file as one "
                 "scene, rename that column", path)
    return table_rows(path, df, named)


def format_table(path: Path, df: pd.DataFrame, reader: str) -> dict[str, Any]:
    """The rows that the track format ``reader`` (its class's dotted path, for the messages) read from ``path``: a
    DataFrame with the columns agent, frame, x, y and optionally those of :data:`TRACK_COLUMNS`, others ignored;
    validated as a table's (:func:`table_rows`)."""
    if missing := [k for k in REQUIRED if k not in df.columns]:
        raise ValueError(f"data.source._target_={reader}: its table of {path} lacks the column(s) {missing}")
    if len(df) == 0:
        raise ValueError(f"{path}: no rows (expected one row per agent per frame)")
    df = df[[k for k in TRACK_COLUMNS if k in df.columns]]
    return table_rows(path, df, {k: k for k in df.columns})


def table_rows(path: Path, df: pd.DataFrame, named: Mapping[str, str]) -> dict[str, Any]:
    """Validate a table's rows (``named``: key -> its column in ``df``); rows sorted by (scene id, agent, frame).

    Returns: scene [R] int64 (index into scene_ids), scene_ids [Z] int64 (each scene's source id, sorted), agent
    [R] int64 (ids or codes), frame [R] int64, xy [R, 2] float64, vel [R, 2] float64 or None,
    agent_class [R] int64 or None, line [R] int64 (each row's index in the file) and names (key -> names
    of string ids: scene, agent, agent_class), has_scene (whether a scene column was read).
    """
    nums = {k: _numbers(path, df[named[k]]) for k in NUMERIC if k in named}
    frame = nums["frame"]
    if (frac := frame != np.round(frame)).any():
        i = int(np.argmax(frac))
        raise ValueError(f"{path}: column {named['frame']!r} has non-integer frames (first on {_row(path, i)}: "
                         f"{float(frame[i])!r})")
    names: dict[str, list[str]] = {}
    agent, agent_names = _ids(path, df[named["agent"]])
    if agent_names is not None:
        names["agent"] = agent_names
    if "scene" in named:
        # scenes in id order (names sorted), so the split and the windows do not depend on the rows' order
        scene_ids, scene_names = _ids(path, df[named["scene"]])
        ids, scene = np.unique(scene_ids, return_inverse=True)
        if scene_names is not None:
            names["scene"] = scene_names
    else:
        scene, ids = np.zeros(len(df), np.int64), np.zeros(1, np.int64)
    klass = None
    if "agent_class" in named:
        klass, names["agent_class"] = _ids(path, df[named["agent_class"]], integers=False)
    order = np.lexsort((frame, agent, scene))
    out = {"scene": scene[order], "scene_ids": ids, "agent": agent[order],
           "frame": frame[order].astype(np.int64), "line": order,
           "xy": np.stack([nums["x"], nums["y"]], 1)[order],
           "vel": np.stack([nums["vx"], nums["vy"]], 1)[order] if "vx" in nums else None,
           "agent_class": None if klass is None else klass[order], "names": names, "has_scene": "scene" in named}
    _check_rows(path, out, named)
    return out


def _check_rows(path: Path, t: dict[str, Any], named: Mapping[str, str]) -> None:
    """Duplicate (scene, agent, frame) rows and agents whose class changes; rows sorted as read_table's."""
    same_agent = (t["scene"][1:] == t["scene"][:-1]) & (t["agent"][1:] == t["agent"][:-1])
    checks = [(same_agent & (t["frame"][1:] == t["frame"][:-1]), "duplicate rows for")]
    if t["agent_class"] is not None:
        checks.append((same_agent & (t["agent_class"][1:] != t["agent_class"][:-1]),
                       f"more than one {named['agent_class']!r} for"))
    for bad, what in checks:
        if bad.any():
            i = int(np.argmax(bad))
            keys = [k for k in ("scene", "agent", "frame") if k in named]
            scene = t["scene_ids"][t["scene"][i]]
            values = {"scene": id_name(t, "scene", scene), "agent": id_name(t, "agent", t["agent"][i]),
                      "frame": int(t["frame"][i])}
            lines = [_row(path, j) for j in sorted(int(t["line"][k]) for k in (i, i + 1))]
            raise ValueError(f"{path}: {what} ({', '.join(repr(named[k]) for k in keys)}) = "
                             f"({', '.join(str(values[k]) for k in keys)}) on {' and '.join(lines)}")


def id_name(t: dict[str, Any], key: str, value: int) -> str:
    names = t["names"].get(key)
    return repr(names[int(value)]) if names is not None else str(int(value))
