"""The ``source`` node of the levelX data sets (``data=ind``, ``round``, ``unid``; ``data.source._target_``:
:class:`LevelXSource`): where the recordings are, which of them, what their files and columns are called and which
road users are kept; and how they are cut and split (DNRI's inD setup: 50-step windows of 2.5 Hz, recordings
19 / 7 / 7 in order)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from dider.data.levelx.reading import DEFAULT_FEATURES
from dider.data.levelx.recordings import pattern_regex
from dider.data.levelx.tracks import LevelXTracks
from dider.data.sources import SourceSettings
from dider.data.windowing import Windows
from dider.validation import Rule, above, optional, text, texts


def _pattern(value: Any) -> str | None:
    if not isinstance(value, str):
        return "expected a file name pattern with one {id}, e.g. {id}_tracks.csv"
    try:
        pattern_regex(str(value))
    except ValueError as e:
        return str(e)
    return None


@dataclass(frozen=True)
class LevelXFiles:
    """Each recording's files, as patterns with one ``{id}`` placeholder."""

    tracks: str = "{id}_tracks.csv"
    tracks_meta: str = "{id}_tracksMeta.csv"
    recording_meta: str = "{id}_recordingMeta.csv"
    background: str = "{id}_background.png"  # the image drawn under the trajectory figures, where present

    SETTINGS: ClassVar[dict[str, Rule]] = {k: _pattern for k in ("tracks", "tracks_meta", "recording_meta",
                                                                  "background")}


@dataclass(frozen=True)
class LevelXColumns:
    """The columns read: tracks' track id, frame and features, tracksMeta's class, recordingMeta's frame rate."""

    track_id: str = "trackId"
    frame: str = "frame"
    agent_class: str = "class"
    frame_rate: str = "frameRate"
    features: tuple[str, ...] = DEFAULT_FEATURES  # x, y (m), x and y velocity (m/s)

    SETTINGS: ClassVar[dict[str, Rule]] = {
        **{k: text for k in ("track_id", "frame", "agent_class", "frame_rate")},
        "features": lambda v: None if isinstance(v, (list, tuple)) and len(v) == 4
        else "need 4 columns (x, y, x velocity, y velocity)"}


def _recording_ids(value: object) -> str | None:
    ok = isinstance(value, (list, tuple)) and all(isinstance(v, (int, str)) and not isinstance(v, bool) for v in value)
    return None if ok else "expected a list of recording ids, e.g. [0, 1, 7]"


@dataclass(frozen=True)
class LevelXSource(SourceSettings):
    """A levelX data set's recordings. Its nested settings (``files``, ``columns``) may be given as mappings, over
    their defaults key by key, and its lists as lists (as a config holds them)."""

    root: str | None = None  # the folder with each recording's files
    name: str = "ind"  # the data set's name: the cache files' prefix and the log messages
    recordings: tuple[int | str, ...] | None = None  # the recording ids used, e.g. [0, 1, 7]; null: every one found
    files: LevelXFiles = LevelXFiles()
    columns: LevelXColumns = LevelXColumns()
    classes: tuple[str, ...] | None = None  # the road-user classes kept, e.g. [car, truck_bus]; null: all (DNRI)
    # metres per background pixel = recordingMeta's orthoPxToMeter x this (inD's images are downscaled 12x)
    background_scale: float = 12.0

    SETTINGS: ClassVar[dict[str, Rule | type]] = {
        "files": LevelXFiles, "columns": LevelXColumns, "background_scale": above(0), "root": optional(text),
        "name": text, "recordings": optional(_recording_ids), "classes": optional(texts)}
    WINDOWS: ClassVar[Windows] = Windows(seq_len=50, downsample=10)  # DNRI's inD windows: 50 steps of 2.5 Hz
    UNUSED: ClassVar[dict[str, str]] = {
        "max_speed": "levelX tracks come from a drone's view: no tracking jumps to drop"}
    SPLIT: ClassVar[tuple[int, ...]] = (19, 7, 7)  # DNRI's: recordings 00-18 / 19-25 / 26-32
    IN_ORDER: ClassVar[bool] = True
    UNITS: ClassVar[str] = "m"

    def where(self) -> str:
        return f"{self.name} (data.source.root={self.root})"

    def open(self, windows: Windows, cache_dir: Path) -> LevelXTracks:
        """The recordings found (read and cached when cut)."""
        return LevelXTracks(self, windows, cache_dir)

    def __post_init__(self) -> None:
        super().__post_init__()  # the settings as given (nested mappings checked key by key), before any conversion
        for key in ("files", "columns"):
            if isinstance(given := getattr(self, key), Mapping):
                nested = {k: tuple(v) if isinstance(v, list) else v for k, v in given.items()}
                object.__setattr__(self, key, NESTED[key](**nested))
        for key in ("recordings", "classes"):
            if isinstance(given := getattr(self, key), list):
                object.__setattr__(self, key, tuple(given))


NESTED = {"files": LevelXFiles, "columns": LevelXColumns}  # the source's nested settings, by key
