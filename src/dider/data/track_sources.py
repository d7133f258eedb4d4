"""The track sources of tables (:class:`~dider.data.tracks.TracksDataModule`'s ``data.source`` nodes whose scenes are
a table's rows, cut by :mod:`dider.data.table`): the classes a data config's ``data.source._target_`` names. Each
says how its data set is cut and split (:class:`TableLayout`: ``WINDOWS``, the windows' defaults; ``UNUSED``, the
window settings it does not read, and why; ``SPLIT``, the split's default; ``IN_ORDER``; ``UNITS``) and gives its
scenes by ``open(windows, cache_dir)`` (:class:`~dider.data.tracks.Tracks`).

- :class:`TrackFile`: a file (or folder) in a format of its own, read into the table's rows by the class's ``read``:
  the base of a track format, dider's (:class:`~dider.data.readers.eth_ucy.EthUcyFiles`) or a user's, whose own
  options are the subclass's fields;
- :class:`TableFile`: a ``.csv`` / ``.parquet`` table whose columns ``columns`` names (``data=table``);
- :class:`KloppySource`: a soccer provider's tracking files through kloppy (``data=soccer``); the frame rate is the
  provider's unless given.

The levelX recordings are a source of their own (:class:`~dider.data.levelx.source.LevelXSource`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import pandas as pd

from dider.data.readers.kloppy import PROVIDERS, kloppy_tracking, tracking_rows
from dider.data.sources import SourceSettings
from dider.data.table import TableTracks
from dider.data.table_reading import DEFAULT_COLUMNS, check_columns, columns_problem, format_table, read_table
from dider.data.windowing import Windows
from dider.targets import class_path
from dider.validation import Rule, above, boolean, finite, one_of

log = logging.getLogger(__name__)

# Two recordings whose frame rates differ by less than this share are read as one rate (kloppy infers some
# providers' rates from the timestamps).
RATE_TOLERANCE = 0.02


def _rate(value: Any) -> str | None:
    return above(0)(value) or finite(value)


class TableLayout:
    """How a table is cut and split (the constants of :mod:`dider.data.track_sources`' sources), and its opening."""

    WINDOWS: ClassVar[Windows] = Windows()
    UNUSED: ClassVar[dict[str, str]] = {
        "eval_stride": "a table is cut before its split: data.windows.stride serves every split"}
    SPLIT: ClassVar[tuple[float, ...]] = (0.8, 0.1, 0.1)  # fractions of the scenes (or windows), seeded
    IN_ORDER: ClassVar[bool] = False

    def open(self, windows: Windows, cache_dir: Path) -> TableTracks:
        """The table's scenes, read on first use (nothing is cached)."""
        return TableTracks(self.rows, self.where, windows)


@dataclass(frozen=True)
class TrackFile(SourceSettings, TableLayout):
    """A file, or a folder of files, of tracks in a format of its own: a subclass (a frozen dataclass, its own options
    its fields, their rules in ``SETTINGS``) defines :meth:`read`; the table's windows, split, normaliser and loader
    do the rest (``data=table``'s: ``UNITS`` and the class constants of :class:`TableLayout` may be overridden)."""

    path: str | None = None  # the file or folder the format reads (required)
    frame_rate: float = 1.0  # frames per second of the frame column: differenced velocities are per second

    SETTINGS: ClassVar[dict[str, Rule | type]] = {"frame_rate": _rate}
    UNITS: ClassVar[str | None] = None  # unknown: the user's

    def read(self, path: Path) -> pd.DataFrame:
        """The tracks at ``path`` (an existing file or folder) as one long table: a DataFrame with the columns agent,
        frame (integer steps), x, y and optionally scene, vx, vy, agent_class, one row per agent per frame; any
        other column is ignored. A problem raises naming the file and line."""
        raise NotImplementedError(f"{class_path(type(self))}: a track format defines read(path)")

    def where(self) -> str:
        """What messages name as the data's origin."""
        return str(self.file())

    def file(self) -> Path:
        if self.path is None:
            raise ValueError(f"data.source.path is not set: point it at what {class_path(type(self))} reads")
        return Path(self.path).expanduser()

    def rows(self) -> tuple[dict[str, Any], float]:
        """The track table's rows (:func:`~dider.data.table_reading.table_rows`) and its frame rate."""
        if not (path := self.file()).exists():
            raise FileNotFoundError(f"data.source.path={path}: no such file or folder")
        return format_table(path, self.read(path), class_path(type(self))), self.frame_rate


@dataclass(frozen=True)
class TableFile(TrackFile):
    """A ``.csv`` / ``.parquet`` table, one row per agent per frame, its columns named by ``columns``."""

    # the table's column names: agent, frame, x, y required; scene, vx, vy, agent_class optional
    columns: Mapping[str, str | None] = field(default_factory=lambda: dict(DEFAULT_COLUMNS))

    SETTINGS: ClassVar[dict[str, Rule | type]] = TrackFile.SETTINGS | {"columns": columns_problem}

    def file(self) -> Path:
        if self.path is None:
            raise ValueError("data.source.path is not set: point it at a .csv or .parquet table with one row per "
                             "agent per frame (columns named in data.source.columns)")
        return Path(self.path).expanduser()

    def rows(self) -> tuple[dict[str, Any], float]:
        return read_table(self.file(), check_columns(self.columns)), self.frame_rate


@dataclass(frozen=True)
class KloppySource(SourceSettings, TableLayout):
    """A match's tracking data read through kloppy (``pip install 'dider[soccer]'``)."""

    provider: str = "hawkeye"  # kloppy's reader: hawkeye, skillcorner, metrica_csv, metrica_epts, tracab, ...
    files: Mapping[str, Any] | None = None  # the reader's files by its argument names, e.g. Hawk-Eye's ball_feeds
    options: Mapping[str, Any] | None = None  # further keyword arguments of the kloppy loader (sample_rate, limit)
    ball: bool = False  # the ball as one more agent (class ``ball``)
    frame_rate: float | None = None  # null: the provider's (a value given must match it)

    SETTINGS: ClassVar[dict[str, Rule]] = {
        "provider": one_of(*sorted(PROVIDERS)), "ball": boolean,
        "frame_rate": lambda value: None if value is None or _rate(value) is None
        else "must be null (the provider's) or a number > 0"}
    UNITS: ClassVar[str | None] = "m"  # kloppy's metric pitch coordinates

    def where(self) -> str:
        files = dict(self.files) if isinstance(self.files, Mapping) else self.files  # checked as it reads
        return f"data.source.provider={self.provider} data.source.files={files or {}}"

    def rows(self) -> tuple[dict[str, Any], float]:
        rows, rate = tracking_rows(kloppy_tracking(self.provider, self.files, self.options), self.ball, self.where())
        if rate is None and self.frame_rate is None:
            raise ValueError(f"{self.where()}: the tracking data give no frame rate; set data.source.frame_rate")
        if rate is not None and self.frame_rate is not None and abs(rate - self.frame_rate) > RATE_TOLERANCE * rate:
            raise ValueError(f"data.source.frame_rate={self.frame_rate} (given, or a checkpoint's in prediction): "
                             f"the tracking data run at {rate} frames per second; leave it null to use theirs (in "
                             f"prediction, set data.source.frame_rate and data.windows.downsample to the same step "
                             f"rate as the checkpoint's, with predict.force=true)")
        rate = self.frame_rate or rate
        log.info("%s: %d players%s over %d period(s) at %s Hz", self.where(), len(rows["names"]["agent"]) -
                 int(self.ball), " and the ball" if self.ball else "", len(rows["scene_ids"]), rate)
        return rows, rate
