"""Finding the recordings of a levelX data set.

A recording is found by its tracks file, whose name matches a pattern with one ``{id}`` placeholder
(``{id}_tracks.csv`` by default); its tracksMeta and recordingMeta files must exist next to it. Recordings
are ordered by id (numerically when every id is a number); the data module splits them in that order.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class RecordingFiles:
    """The three CSV files of one recording."""

    id: str
    tracks: Path
    tracks_meta: Path
    recording_meta: Path

    def signature(self) -> list[tuple[str, int, int]]:
        """(name, size, mtime_ns) of each file: a changed file changes the cache key."""
        return [(p.name, p.stat().st_size, p.stat().st_mtime_ns)
                for p in (self.tracks, self.tracks_meta, self.recording_meta)]


def pattern_regex(pattern: str) -> re.Pattern[str]:
    if pattern.count("{id}") != 1:
        raise ValueError(f"file pattern {pattern!r}: must contain '{{id}}' exactly once, e.g. "
                         f"'{{id}}_tracks.csv'")
    return re.compile(re.escape(pattern).replace(re.escape("{id}"), "(?P<id>.+)") + r"\Z")


def _sort_ids(ids: list[str]) -> list[str]:
    """Recording order: numeric when every id is a number ('2' before '10'), else lexicographic."""
    return sorted(ids, key=int) if all(i.isdigit() for i in ids) else sorted(ids)


def discover_recordings(
    root: Path,
    tracks_pattern: str = "{id}_tracks.csv",
    tracks_meta_pattern: str = "{id}_tracksMeta.csv",
    recording_meta_pattern: str = "{id}_recordingMeta.csv",
    recordings: Sequence[int | str] | None = None,
) -> list[RecordingFiles]:
    """The recordings under ``root`` in recording order (all found, or the listed ones).

    A recording is found by its tracks file; its two metadata files must exist next to it.
    """
    if not root.is_dir():
        raise FileNotFoundError(f"data.source.root={root}: no such folder (point it at the folder holding the "
                                f"{tracks_pattern.format(id='XX')} files)")
    regex = pattern_regex(tracks_pattern)
    for p in (tracks_meta_pattern, recording_meta_pattern):
        pattern_regex(p)
    found = {m["id"]: m for p in root.iterdir() if (m := regex.match(p.name))}
    ids = _sort_ids(list(found))
    if recordings is not None:
        # Ints match numeric ids regardless of zero padding (3 -> '03'); strings match exactly.
        by_int = {int(i): i for i in ids if i.isdigit()}
        chosen = []
        for r in recordings:
            rid = str(r) if str(r) in found else by_int.get(int(r)) if str(r).isdigit() else None
            if rid is None:
                raise FileNotFoundError(
                    f"data.source.recordings: recording {r!r} has no {tracks_pattern.format(id=r)} in {root}")
            chosen.append(rid)
        ids = _sort_ids(list(dict.fromkeys(chosen)))
    if not ids:
        raise FileNotFoundError(f"data.source.root={root}: no files matching {tracks_pattern.format(id='*')}")
    out = []
    for i in ids:
        files = RecordingFiles(i, root / tracks_pattern.format(id=i), root / tracks_meta_pattern.format(id=i),
                               root / recording_meta_pattern.format(id=i))
        for path in (files.tracks_meta, files.recording_meta):
            if not path.is_file():
                raise FileNotFoundError(f"{path}: missing (recording {i} has {files.tracks.name})")
        out.append(files)
    return out
