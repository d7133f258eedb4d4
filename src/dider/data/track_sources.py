"""The ``source`` node of the data sets of long tracks (:class:`~dider.data.tracks.TracksDataModule`): the reader
and what it reads. Each source's class says how its data set is cut and split: ``WINDOWS`` (the windows' defaults),
``UNUSED`` (the window settings it does not read, and why), ``SPLIT`` (the split's default), ``IN_ORDER`` (its scenes
are recordings split in order before the cut; else a table's, cut and then split by a seeded permutation), ``UNITS``;
``open(windows, cache_dir)`` gives its scenes (:class:`~dider.data.tracks.Tracks`).

- :class:`FileSource`: a ``.csv`` / ``.parquet`` table whose columns ``columns`` names (reader ``table``), or the
  files a track reader of :mod:`dider.data.readers` reads (``eth_ucy``, or a new format's module).
- :class:`KloppySource`: a soccer provider's tracking files through kloppy (reader ``kloppy``); the frame rate is
  the provider's unless given.
- :class:`~dider.data.levelx.source.LevelXSource`: the inD / rounD / uniD recordings (reader ``levelx``).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from dider.data.common import source_node
from dider.data.levelx.source import LevelXSource
from dider.data.readers import reader_problem
from dider.data.readers.kloppy import PROVIDERS, kloppy_tracking, tracking_rows
from dider.data.table import TableTracks
from dider.data.table_reading import DEFAULT_COLUMNS, check_columns, columns_problem, read_table
from dider.data.windowing import Windows
from dider.validation import PickedBy, Rule, above, boolean, finite, one_of

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
class FileSource(TableLayout):
    """A table file, or what a track reader reads."""

    reader: str = "table"  # ``table`` or a track reader's module name (dider.data.readers)
    path: str | None = None  # the .csv / .parquet file, or the file or folder the reader reads
    # the table's column names (reader table): agent, frame, x, y required; scene, vx, vy, agent_class optional
    columns: Mapping[str, str | None] = field(default_factory=lambda: dict(DEFAULT_COLUMNS))
    frame_rate: float = 1.0  # frames per second of the frame column: differenced velocities are per second

    SETTINGS: ClassVar[dict[str, Rule]] = {"reader": lambda v: reader_problem(v, tuple(SOURCES)),
                                           "frame_rate": _rate, "columns": columns_problem}
    UNITS: ClassVar[str | None] = None  # unknown: the user's

    def __post_init__(self) -> None:
        check_columns(self.columns)  # before anything is read

    def where(self) -> str:
        """What messages name as the data's origin."""
        return str(self.file())

    def file(self) -> Path:
        if self.path is None:
            raise ValueError("data.source.path is not set: point it at a .csv or .parquet table with one row per "
                             "agent per frame (columns named in data.source.columns), or at what "
                             "data.source.reader reads")
        return Path(self.path).expanduser()

    def rows(self) -> tuple[dict[str, Any], float]:
        """The track table's rows and its frame rate."""
        return read_table(self.file(), check_columns(self.columns), self.reader), self.frame_rate


@dataclass(frozen=True)
class KloppySource(TableLayout):
    """A match's tracking data read through kloppy (``pip install 'dider[soccer]'``)."""

    reader: str = "kloppy"
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


TrackSource = FileSource | KloppySource | LevelXSource
# the readers with settings of their own; any other: FileSource
SOURCES: dict[str, type] = {"kloppy": KloppySource, "levelx": LevelXSource}
PICK = PickedBy("reader", lambda: SOURCES, default="table", fallback=FileSource)  # a source's class by its reader


def track_source(given: Mapping[str, Any] | None) -> TrackSource:
    """The ``data.source`` node as its reader's settings, checked: unknown keys and bad values raise naming them."""
    given = dict(given or {})
    cls = PICK.pick(given, "data.source")
    return cls.of(given) if hasattr(cls, "of") else source_node(cls(), given)
