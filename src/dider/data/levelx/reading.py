"""Reading and validating the CSV files of one levelX recording.

Only the needed columns are read (extra ones are ignored). Bad input raises ValueError naming the file,
the column and, where there is one, the CSV line: unreadable files, missing columns, unparsable / NaN /
inf values, non-integer ids or frames, duplicate (trackId, frame) rows, tracksMeta that disagrees with
tracks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dider.data.columns import check_finite, csv_header, read_columns
from dider.data.levelx.recordings import RecordingFiles

DEFAULT_FEATURES = ("xCenter", "yCenter", "xVelocity", "yVelocity")


@dataclass(frozen=True)
class WindowParams:
    """Everything that changes the windows cut from a recording (part of the cache key)."""

    track_id_column: str = "trackId"
    frame_column: str = "frame"
    class_column: str = "class"
    frame_rate_column: str = "frameRate"
    features: tuple[str, ...] = DEFAULT_FEATURES
    classes: tuple[str, ...] | None = None
    downsample: int = 10
    seq_len: int = 50
    stride: int = 50
    min_agent_steps: int = 1
    min_agents: int = 2
    max_agents: int | None = None


def read_tracks(files: RecordingFiles, p: WindowParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> track id [R] int64, frame [R] int64, features [R, 4] float64 for every row of XX_tracks.csv."""
    cols = [p.track_id_column, p.frame_column, *p.features]
    df = read_columns(files.tracks, cols)
    check_finite(files.tracks, df, cols, integer=cols[:2])
    tid = df[p.track_id_column].to_numpy().astype(np.int64)
    frame = df[p.frame_column].to_numpy().astype(np.int64)
    if (frame < 0).any():
        raise ValueError(f"{files.tracks}: column {p.frame_column!r} has negative frames "
                         f"(first on line {int(np.argmax(frame < 0)) + 2})")
    feats = df[list(p.features)].to_numpy()
    big = np.abs(feats) > np.finfo(np.float32).max  # would turn into inf in the float32 windows
    if big.any():
        row, col = (int(i[0]) for i in np.nonzero(big))
        raise ValueError(f"{files.tracks}: column {p.features[col]!r} has values beyond the float32 range "
                         f"(first on line {row + 2}: {feats[row, col]!r})")
    return tid, frame, feats


def read_tracks_meta(files: RecordingFiles, p: WindowParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> meta track ids [K] (sorted), (initialFrame, finalFrame, numFrames) [K, 3] int64, class [K] str."""
    numeric = [p.track_id_column, "initialFrame", "finalFrame", "numFrames"]
    df = read_columns(files.tracks_meta, numeric, [p.class_column])
    check_finite(files.tracks_meta, df, numeric, integer=numeric)
    if df[p.class_column].isna().any():
        row = int(np.argmax(df[p.class_column].isna().to_numpy()))
        raise ValueError(f"{files.tracks_meta}: column {p.class_column!r} is empty on line {row + 2}")
    ids = df[p.track_id_column].to_numpy().astype(np.int64)
    order = np.argsort(ids, kind="stable")
    ids = ids[order]
    dup = ids[1:] == ids[:-1]
    if dup.any():
        raise ValueError(f"{files.tracks_meta}: trackId {int(ids[1:][dup][0])} is listed more than once")
    frames = df[numeric[1:]].to_numpy().astype(np.int64)[order]
    return ids, frames, df[p.class_column].to_numpy(dtype=object)[order].astype(str)


def frame_rate(files: RecordingFiles, p: WindowParams) -> tuple[float, int | None]:
    """-> (frameRate, locationId or None) from XX_recordingMeta.csv."""
    optional = ["locationId"] if "locationId" in csv_header(files.recording_meta) else []
    df = read_columns(files.recording_meta, [p.frame_rate_column, *optional])
    if len(df) == 0:
        raise ValueError(f"{files.recording_meta}: no rows (expected one row describing the recording)")
    check_finite(files.recording_meta, df, [p.frame_rate_column])
    rate = float(df[p.frame_rate_column].iloc[0])
    if rate <= 0:
        raise ValueError(f"{files.recording_meta}: column {p.frame_rate_column!r} = {rate}: must be > 0")
    loc = df["locationId"].iloc[0] if "locationId" in df else None
    return rate, None if loc is None or not np.isfinite(loc) else int(loc)


def check_consistency(files: RecordingFiles, tid: np.ndarray, frame: np.ndarray, meta_ids: np.ndarray,
                       meta_frames: np.ndarray) -> None:
    """Duplicate (trackId, frame) rows and tracks vs tracksMeta (ids, first/last frame, contiguous count).

    tid, frame: [R]; meta_ids: [K] sorted; meta_frames: [K, 3] (initialFrame, finalFrame, numFrames).
    """
    order = np.lexsort((frame, tid))
    t_s, f_s = tid[order], frame[order]
    dup = (t_s[1:] == t_s[:-1]) & (f_s[1:] == f_s[:-1])
    if dup.any():
        i = int(np.argmax(dup))
        lines = sorted(int(order[j]) + 2 for j in (i, i + 1))
        raise ValueError(f"{files.tracks}: duplicate row for (trackId, frame) = ({int(t_s[i])}, "
                         f"{int(f_s[i])}) on lines {lines}")
    ids, first_idx, counts = np.unique(t_s, return_index=True, return_counts=True)
    unknown = np.setdiff1d(ids, meta_ids)
    if unknown.size:
        raise ValueError(f"{files.tracks}: trackId(s) {unknown[:5].tolist()} have no row in "
                         f"{files.tracks_meta.name}")
    absent = np.setdiff1d(meta_ids, ids)
    if absent.size:
        raise ValueError(f"{files.tracks_meta}: trackId(s) {absent[:5].tolist()} have no rows in "
                         f"{files.tracks.name}")
    m = meta_frames  # the id sets are equal and both sorted, so rows align
    first, last = f_s[first_idx], f_s[first_idx + counts - 1]
    checks = [
        ("numFrames", m[:, 2] != m[:, 1] - m[:, 0] + 1, "numFrames != finalFrame - initialFrame + 1"),
        ("initialFrame", first != m[:, 0], "initialFrame != the track's first frame in tracks"),
        ("finalFrame", last != m[:, 1], "finalFrame != the track's last frame in tracks"),
        ("numFrames", counts != m[:, 2], "numFrames != the track's number of rows in tracks (gaps?)"),
    ]
    for col, bad, what in checks:
        if bad.any():
            k = int(np.argmax(bad))
            raise ValueError(f"{files.tracks_meta}: column {col!r} inconsistent with {files.tracks.name} for "
                             f"trackId {int(ids[k])}: {what} (meta {m[k].tolist()}, tracks first "
                             f"{int(first[k])}, last {int(last[k])}, rows {int(counts[k])})")
