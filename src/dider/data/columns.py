"""Reading named columns of a CSV file, with errors that name the file, the column and the CSV line.

Only the named columns are read (extra ones are ignored); numbers are read as float64 and checked for
NaN, inf and, in id and frame columns, non-integers.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd


def csv_header(path: Path) -> list[str]:
    try:
        return list(pd.read_csv(path, nrows=0).columns)
    except pd.errors.EmptyDataError as e:
        raise ValueError(f"{path}: empty file (expected a CSV header)") from e
    except (ValueError, OSError) as e:  # e.g. binary garbage, a bad encoding
        raise ValueError(f"{path}: not a readable CSV file ({type(e).__name__}: {e})") from e


def read_columns(path: Path, numeric: Sequence[str], text: Sequence[str] = ()) -> pd.DataFrame:
    """Read only the named columns (extras ignored); numbers as float64 (checked later for NaN/inf/ints)."""
    header = csv_header(path)
    missing = [c for c in [*numeric, *text] if c not in header]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing} (found {list(header)})")
    dtype: dict[str, Any] = {c: np.float64 for c in numeric} | {c: str for c in text}
    try:
        return pd.read_csv(path, usecols=[*numeric, *text], dtype=dtype, engine="c")
    except ValueError as e:  # e.g. a word, or a padded " nan", in a numeric column: find the cell
        raise ValueError(first_bad_number(path, numeric) or f"{path}: could not parse columns {list(numeric)} as "
                         f"numbers: {e}") from e


def first_bad_number(path: Path, numeric: Sequence[str]) -> str | None:
    """'file: column c, line n: 'value' is not a number' for the first cell of ``numeric`` that does not parse."""
    raw = pd.read_csv(path, usecols=list(numeric), dtype=str, keep_default_na=False, engine="c")
    for col in numeric:
        parsed = pd.to_numeric(raw[col], errors="coerce")
        bad = parsed.isna().to_numpy()
        if bad.any():
            row = int(np.argmax(bad))
            return f"{path}: column {col!r}, line {row + 2}: {raw[col].iloc[row]!r} is not a number"
    return None


def check_finite(path: Path, df: pd.DataFrame, columns: Sequence[str], integer: Sequence[str] = ()) -> None:
    """NaN/inf (and non-integers in id/frame columns) raise, naming file, column and CSV line."""
    for col in columns:
        a = df[col].to_numpy()
        bad = ~np.isfinite(a)
        if col in integer:
            bad |= np.where(bad, False, a != np.round(a))
        if bad.any():
            row = int(np.argmax(bad))
            raise ValueError(f"{path}: column {col!r} has {int(bad.sum())} missing, NaN, inf or (for ids and "
                             f"frames) non-integer values (first on line {row + 2}: {a[row]!r})")
