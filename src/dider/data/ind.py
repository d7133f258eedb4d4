"""inD (and rounD / uniD: the same levelXdata schema) read from the raw per-recording CSV files.

DNRI's protocol by default (design.md section 4, research/data.md section 1.5): recordings in sorted order
split 19 / 7 / 7 into train / val / test, features [xCenter, yCenter, xVelocity, yVelocity] (metres, m/s),
25 Hz downsampled by 10 to 2.5 Hz, all road-user classes, min/max normalisation fitted on the present
agents of the train split, burn-in 5 per agent (``burn_in_mode=per_agent``: each agent is observed for its
own first 5 present steps, then rolled out; see RelationalVAE.rollout).

Each recording is cut into windows of ``seq_len`` downsampled steps (every ``stride`` steps). A window keeps
the tracks present in it (at least ``min_agent_steps`` of its steps), ordered by trackId, with a
presence mask [T, N]: agents enter and leave mid-window. Windows with fewer than ``min_agents`` agents
(default 2: a relation needs two) are dropped. Windows have different agent counts, so they are stored
packed (one row per agent per window) and padded to the largest count of each batch.

Preprocessing (read, validate, downsample, window) runs once per recording and is cached under
``cache_dir/levelx/``, keyed by the source files' sizes and modification times and by every parameter that
changes the windows, so runs with the same settings share it and a changed file is re-read. Caches are
written atomically (a killed run leaves no half-written file).

Bad input raises ValueError / FileNotFoundError naming the file and column before any training: missing
files or columns, unparsable / NaN / inf values, duplicate (trackId, frame) rows, tracksMeta that
disagrees with tracks, a split that needs more recordings than exist, recordings too short for one window.
"""

from __future__ import annotations

import logging
import re
import tempfile
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import matplotlib.image as plt_image
import numpy as np
import pandas as pd
import torch

from dider.data.batch import Normalizer
from dider.data.cache import atomic_torch_save, cache_key
from dider.data.common import (
    SPLITS,
    ClipDataModule,
    PackedClipDataset,
    check_burn_in_mode,
    check_counts,
    check_horizons,
    default_cache_dir,
    fill_absent,
    pad_collate,
    ragged_rows,
    spread_indices,
)
from dider.data.pairs import PairRules, find_pairs

log = logging.getLogger(__name__)

CACHE_VERSION = 1
DEFAULT_FEATURES = ("xCenter", "yCenter", "xVelocity", "yVelocity")
# Cap on the dense (steps x tracks) grid of one recording: a real one has ~4k steps x ~400 tracks.
MAX_GRID_CELLS = 2**28


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


# ---------------------------------------------------------------------------------------------- discovery


def _pattern_regex(pattern: str) -> re.Pattern[str]:
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
        raise FileNotFoundError(f"data.root={root}: no such folder (point it at the folder holding the "
                                f"{tracks_pattern.format(id='XX')} files)")
    regex = _pattern_regex(tracks_pattern)
    for p in (tracks_meta_pattern, recording_meta_pattern):
        _pattern_regex(p)
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
                    f"data.recordings: recording {r!r} has no {tracks_pattern.format(id=r)} in {root}")
            chosen.append(rid)
        ids = _sort_ids(list(dict.fromkeys(chosen)))
    if not ids:
        raise FileNotFoundError(f"data.root={root}: no files matching {tracks_pattern.format(id='*')}")
    out = []
    for i in ids:
        files = RecordingFiles(i, root / tracks_pattern.format(id=i), root / tracks_meta_pattern.format(id=i),
                               root / recording_meta_pattern.format(id=i))
        for path in (files.tracks_meta, files.recording_meta):
            if not path.is_file():
                raise FileNotFoundError(f"{path}: missing (recording {i} has {files.tracks.name})")
        out.append(files)
    return out


def split_counts(split: Sequence[float], available: int) -> tuple[int, int, int]:
    """Recordings per split from counts (ints, e.g. DNRI's [19, 7, 7]) or fractions (all < 1, e.g. [0.6,
    0.2, 0.2]; val and test get at least one each, train the rest). Counts may leave recordings unused."""
    if len(split) != 3:
        raise ValueError(f"data.split={list(split)}: expected three entries (train, val, test)")
    if all(0 < float(s) < 1 for s in split):
        val, test = (max(1, round(float(s) * available)) for s in split[1:])
        counts = (available - val - test, val, test)
    elif all(float(s) == int(s) for s in split):
        counts = tuple(int(s) for s in split)
    else:
        raise ValueError(f"data.split={list(split)}: give recording counts (ints) or fractions (all in "
                         f"(0, 1))")
    if min(counts) < 1:
        raise ValueError(f"data.split={list(split)}: every split needs >= 1 recording (got {list(counts)} "
                         f"from {available} recordings)")
    if sum(counts) > available:
        raise ValueError(f"data.split={list(split)} asks for {sum(counts)} recordings but only {available} "
                         f"were found")
    return counts  # type: ignore[return-value]


# ---------------------------------------------------------------------------------------------- reading


def _header(path: Path) -> list[str]:
    try:
        return list(pd.read_csv(path, nrows=0).columns)
    except pd.errors.EmptyDataError as e:
        raise ValueError(f"{path}: empty file (expected a CSV header)") from e
    except (ValueError, OSError) as e:  # e.g. binary garbage, a bad encoding
        raise ValueError(f"{path}: not a readable CSV file ({type(e).__name__}: {e})") from e


def _read_columns(path: Path, numeric: Sequence[str], text: Sequence[str] = ()) -> pd.DataFrame:
    """Read only the named columns (extras ignored); numbers as float64 (checked later for NaN/inf/ints)."""
    header = _header(path)
    missing = [c for c in [*numeric, *text] if c not in header]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing} (found {list(header)})")
    dtype: dict[str, Any] = {c: np.float64 for c in numeric} | {c: str for c in text}
    try:
        return pd.read_csv(path, usecols=[*numeric, *text], dtype=dtype, engine="c")
    except ValueError as e:  # e.g. a word in a numeric column
        raise ValueError(f"{path}: could not parse columns {[*numeric, *text]} as numbers: {e}") from e


def _finite(path: Path, df: pd.DataFrame, columns: Sequence[str], integer: Sequence[str] = ()) -> None:
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


def _read_tracks(files: RecordingFiles, p: WindowParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> track id [R] int64, frame [R] int64, features [R, 4] float64 for every row of XX_tracks.csv."""
    cols = [p.track_id_column, p.frame_column, *p.features]
    df = _read_columns(files.tracks, cols)
    _finite(files.tracks, df, cols, integer=cols[:2])
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


def _read_tracks_meta(files: RecordingFiles, p: WindowParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> meta track ids [K] (sorted), (initialFrame, finalFrame, numFrames) [K, 3] int64, class [K] str."""
    numeric = [p.track_id_column, "initialFrame", "finalFrame", "numFrames"]
    df = _read_columns(files.tracks_meta, numeric, [p.class_column])
    _finite(files.tracks_meta, df, numeric, integer=numeric)
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


def _frame_rate(files: RecordingFiles, p: WindowParams) -> tuple[float, int | None]:
    """-> (frameRate, locationId or None) from XX_recordingMeta.csv."""
    optional = ["locationId"] if "locationId" in _header(files.recording_meta) else []
    df = _read_columns(files.recording_meta, [p.frame_rate_column, *optional])
    if len(df) == 0:
        raise ValueError(f"{files.recording_meta}: no rows (expected one row describing the recording)")
    _finite(files.recording_meta, df, [p.frame_rate_column])
    rate = float(df[p.frame_rate_column].iloc[0])
    if rate <= 0:
        raise ValueError(f"{files.recording_meta}: column {p.frame_rate_column!r} = {rate}: must be > 0")
    loc = df["locationId"].iloc[0] if "locationId" in df else None
    return rate, None if loc is None or not np.isfinite(loc) else int(loc)


def _check_consistency(files: RecordingFiles, tid: np.ndarray, frame: np.ndarray, meta_ids: np.ndarray,
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


# ---------------------------------------------------------------------------------------------- windows


def preprocess_recording(files: RecordingFiles, p: WindowParams) -> dict[str, Any]:
    """Read and validate one recording and cut its windows (raw units, packed).

    Returns a dict of: states [P, T, 4] float32 (zeros where absent), mask [P, T] bool, offsets [W+1]
    long (window w owns rows offsets[w]:offsets[w+1], agents by trackId), track_id [P] long,
    agent_class [P] long (index into class_names), class_names list[str], window_start [W] long
    (downsampled step), frame_rate, location_id, recording, num_steps (downsampled), num_tracks.
    """
    tid, frame, feats = _read_tracks(files, p)
    meta_ids, meta_frames, meta_class = _read_tracks_meta(files, p)
    rate, location = _frame_rate(files, p)
    _check_consistency(files, tid, frame, meta_ids, meta_frames)

    # Downsample on absolute frame numbers (DNRI's feats[::10] from frame 0), then drop filtered classes.
    keep = frame % p.downsample == 0
    if p.classes is not None:
        keep &= np.isin(tid, meta_ids[np.isin(meta_class, p.classes)])
    tid, step, feats = tid[keep], frame[keep] // p.downsample, feats[keep]
    class_names = sorted(set(meta_class.tolist()))
    out = _empty_windows(p, class_names, rate, location, files.id)
    if tid.size == 0:
        return out

    # Dense grid of the recording: [S steps, K tracks]. Column order = sorted trackId = agent order.
    tracks, k = np.unique(tid, return_inverse=True)
    num_steps = int(step.max()) + 1
    if num_steps * tracks.size > MAX_GRID_CELLS:
        raise ValueError(f"{files.tracks}: column {p.frame_column!r} reaches frame {int(frame.max())}: "
                         f"{num_steps} steps x {tracks.size} tracks is implausibly large for one recording")
    grid = np.zeros((num_steps, tracks.size, 4), np.float32)
    present = np.zeros((num_steps, tracks.size), bool)
    grid[step, k] = feats
    present[step, k] = True
    out["num_steps"], out["num_tracks"] = num_steps, int(tracks.size)

    starts = np.arange(0, num_steps - p.seq_len + 1, p.stride)
    if starts.size == 0:
        return out
    # Steps each track is present in each window, from a cumulative sum over time: [W, K].
    csum = np.zeros((num_steps + 1, tracks.size), np.int32)
    np.cumsum(present, axis=0, out=csum[1:])
    steps_in = csum[starts + p.seq_len] - csum[starts]
    kept = steps_in >= p.min_agent_steps
    if p.max_agents is not None:
        # Keep the agents seen longest in the window (ties: lower trackId): rank them per window.
        k_all = tracks.size
        score = np.where(kept, steps_in.astype(np.int64) * (k_all + 1) + (k_all - np.arange(k_all)), -1)
        order = np.argsort(-score, axis=1, kind="stable")
        rank = np.empty_like(order)
        np.put_along_axis(rank, order, np.arange(k_all)[None, :].repeat(len(starts), 0), axis=1)
        kept &= rank < p.max_agents
    good = kept.sum(1) >= p.min_agents
    starts, kept = starts[good], kept[good]
    w, a = np.nonzero(kept)  # row-major: by window, then by trackId
    t_idx = starts[w][:, None] + np.arange(p.seq_len)[None, :]  # [P, T]
    offsets = np.zeros(len(starts) + 1, np.int64)
    offsets[1:] = np.cumsum(kept.sum(1))
    code = np.searchsorted(class_names, meta_class[np.searchsorted(meta_ids, tracks)])
    out.update(
        states=torch.from_numpy(grid[t_idx, a[:, None]]),
        mask=torch.from_numpy(present[t_idx, a[:, None]]),
        offsets=torch.from_numpy(offsets),
        track_id=torch.from_numpy(tracks[a]),
        agent_class=torch.from_numpy(code[a].astype(np.int64)),
        window_start=torch.from_numpy(starts.astype(np.int64)),
    )
    return out


def _empty_windows(p: WindowParams, class_names: list[str], rate: float, location: int | None,
                   rec: str) -> dict[str, Any]:
    return {
        "states": torch.zeros(0, p.seq_len, 4), "mask": torch.zeros(0, p.seq_len, dtype=torch.bool),
        "offsets": torch.zeros(1, dtype=torch.long), "track_id": torch.zeros(0, dtype=torch.long),
        "agent_class": torch.zeros(0, dtype=torch.long), "class_names": class_names,
        "window_start": torch.zeros(0, dtype=torch.long), "frame_rate": rate, "location_id": location,
        "recording": rec, "num_steps": 0, "num_tracks": 0,
    }


def concat_windows(blobs: list[dict[str, Any]]) -> dict[str, Any]:
    """Join the packed windows of several recordings (offsets shifted, class codes remapped to one
    sorted vocabulary). Adds window_recording [W] (index into ``recordings``)."""
    names = sorted(set().union(*(b["class_names"] for b in blobs)))
    offsets = [torch.zeros(1, dtype=torch.long)]
    shift = 0
    for b in blobs:
        offsets.append(b["offsets"][1:] + shift)
        shift += int(b["offsets"][-1])
    lut = [torch.tensor([names.index(c) for c in b["class_names"]] or [0], dtype=torch.long) for b in blobs]
    return {
        "states": torch.cat([b["states"] for b in blobs]),
        "mask": torch.cat([b["mask"] for b in blobs]),
        "offsets": torch.cat(offsets),
        "track_id": torch.cat([b["track_id"] for b in blobs]),
        "agent_class": torch.cat([m[b["agent_class"]] for m, b in zip(lut, blobs, strict=True)]),
        "class_names": names,
        "window_start": torch.cat([b["window_start"] for b in blobs]),
        "window_recording": torch.cat([torch.full((len(b["window_start"]),), i, dtype=torch.long)
                                       for i, b in enumerate(blobs)]),
        "recordings": [b["recording"] for b in blobs],
    }


def select_windows(data: dict[str, Any], idx: torch.Tensor) -> dict[str, Any]:
    """The windows ``idx`` [K] long of a packed split (as made by :func:`concat_windows`)."""
    rows, offsets = ragged_rows(data["offsets"], idx)
    out = dict(data, offsets=offsets, window_start=data["window_start"][idx],
               window_recording=data["window_recording"][idx])
    for key in ("states", "mask", "track_id", "agent_class"):
        out[key] = data[key][rows]
    return out


# ---------------------------------------------------------------------------------------------- module


class InDDataModule(ClipDataModule):
    """inD / rounD / uniD windows from the raw CSV files (see the module docstring).

    Batches: states [B, T, N, 4] (normalised; zeros for absent agents), mask [B, T, N] bool; N is the
    largest agent count in the batch. No ground-truth edges. After ``setup``: ``normalizer``,
    ``datasets`` (PackedClipDataset per split with extra attributes track_id, agent_class, class_names,
    window_start, window_recording, recordings), ``dt`` (seconds per step).
    """

    collate_fn = staticmethod(pad_collate)

    def __init__(
        self,
        root: str | None = None,
        name: str = "ind",
        recordings: Sequence[int | str] | None = None,
        split: Sequence[float] = (19, 7, 7),
        tracks_pattern: str = "{id}_tracks.csv",
        tracks_meta_pattern: str = "{id}_tracksMeta.csv",
        recording_meta_pattern: str = "{id}_recordingMeta.csv",
        track_id_column: str = "trackId",
        frame_column: str = "frame",
        class_column: str = "class",
        frame_rate_column: str = "frameRate",
        features: Sequence[str] = DEFAULT_FEATURES,
        classes: Sequence[str] | None = None,
        downsample: int = 10,
        seq_len: int = 50,
        stride: int | None = None,
        eval_stride: int | None = None,
        burn_in: int = 5,
        horizons: Sequence[int] = (1, 20, 40),
        min_agent_steps: int = 1,
        min_agents: int = 2,
        max_agents: int | None = None,
        num_train: int | None = None,
        num_val: int | None = None,
        num_test: int | None = None,
        batch_size: int = 8,
        eval_batch_size: int = 8,
        num_workers: int = 0,
        pin_memory: bool = False,
        cache_dir: str | None = None,
        burn_in_mode: str = "per_agent",
        pairs: dict[str, Any] | None = None,
        background_pattern: str = "{id}_background.png",
        background_scale: float = 12.0,
    ) -> None:
        """pairs: the consistency check's rules (:class:`dider.data.pairs.PairRules` fields); test batches
        carry ``pair_kind``."""
        super().__init__()
        check_burn_in_mode(burn_in_mode)
        try:
            self.pair_rules = PairRules(**{k: tuple(v) if isinstance(v, list | tuple) else v
                                           for k, v in dict(pairs or {}).items()})
        except TypeError as e:
            raise ValueError(f"data.pairs: {e} (fields: {list(PairRules.__dataclass_fields__)})") from None
        check_counts(
            downsample=(downsample, 1), seq_len=(seq_len, 2), stride=(stride, 1),
            eval_stride=(eval_stride, 1), min_agent_steps=(min_agent_steps, 1), min_agents=(min_agents, 1),
            max_agents=(max_agents, min_agents), num_train=(num_train, 1), num_val=(num_val, 1),
            num_test=(num_test, 1), batch_size=(batch_size, 1), eval_batch_size=(eval_batch_size, 1),
            num_workers=(num_workers, 0),
        )
        if min_agent_steps > seq_len:
            raise ValueError(f"data.min_agent_steps={min_agent_steps}: must be <= data.seq_len={seq_len}")
        if len(features) != 4:
            raise ValueError(f"data.features={list(features)}: need 4 columns (x, y, x velocity, y velocity)")
        check_horizons(horizons, seq_len, burn_in)
        for key, pattern in [("tracks_pattern", tracks_pattern), ("tracks_meta_pattern", tracks_meta_pattern),
                             ("recording_meta_pattern", recording_meta_pattern)]:
            try:
                _pattern_regex(pattern)
            except ValueError as e:
                raise ValueError(f"data.{key}: {e}") from None
        split_counts(split, available=10**9)  # form only; the recording count is known in prepare_data
        self.save_hyperparameters(logger=False)
        self.cache_dir = Path(cache_dir) if cache_dir else default_cache_dir()
        self.dt: float | None = None

    # -- files and cache

    def _root(self) -> Path:
        if self.hparams.root is None:
            raise ValueError(f"data.root is not set: point it at the folder with the {self.hparams.name} "
                             f"recordings ({self.hparams.tracks_pattern.format(id='XX')}, ...)")
        return Path(self.hparams.root).expanduser()

    def split_recordings(self) -> dict[str, list[RecordingFiles]]:
        """Recordings of each split, in recording order: the first counts[0] train, then val, then test."""
        h = self.hparams
        recs = discover_recordings(self._root(), h.tracks_pattern, h.tracks_meta_pattern,
                                   h.recording_meta_pattern, h.recordings)
        counts = split_counts(h.split, len(recs))
        if sum(counts) < len(recs):
            log.info("%s: using %d of %d recordings (data.split=%s)", h.name, sum(counts), len(recs),
                     list(h.split))
        bounds = np.cumsum([0, *counts])
        return {s: recs[bounds[i]:bounds[i + 1]] for i, s in enumerate(SPLITS)}

    def window_params(self, split: str) -> WindowParams:
        h = self.hparams
        stride = h.stride if split == "train" else h.eval_stride
        return WindowParams(
            track_id_column=h.track_id_column, frame_column=h.frame_column, class_column=h.class_column,
            frame_rate_column=h.frame_rate_column, features=tuple(h.features),
            classes=None if h.classes is None else tuple(sorted(h.classes)), downsample=h.downsample,
            seq_len=h.seq_len, stride=stride or h.seq_len, min_agent_steps=h.min_agent_steps,
            min_agents=h.min_agents, max_agents=h.max_agents,
        )

    def cache_path(self, files: RecordingFiles, params: WindowParams) -> Path:
        key = cache_key({"version": CACHE_VERSION, "recording": files.id, "files": files.signature(),
                         "params": asdict(params)})
        return self.cache_dir / "levelx" / f"{self.hparams.name}_{files.id}_{key}.pt"

    def _load_or_build(self, files: RecordingFiles, params: WindowParams) -> dict[str, Any]:
        path = self.cache_path(files, params)
        if path.exists():
            return torch.load(path)
        t0 = time.perf_counter()
        blob = preprocess_recording(files, params)
        atomic_torch_save(blob, path)
        log.info("%s recording %s: %d windows from %d tracks in %.1f s -> %s", self.hparams.name, files.id,
                 len(blob["window_start"]), blob["num_tracks"], time.perf_counter() - t0, path)
        return blob

    def prepare_data(self) -> None:
        """Read, validate and cache every recording once (rank 0 only under DDP)."""
        for split, recs in self.split_recordings().items():
            params = self.window_params(split)
            for files in recs:
                if not self.cache_path(files, params).exists():
                    self._load_or_build(files, params)

    def setup(self, stage: str | None = None) -> None:
        if self.datasets:
            return
        h = self.hparams
        raw: dict[str, dict[str, Any]] = {}
        rates: dict[str, float] = {}
        for split, recs in self.split_recordings().items():
            params = self.window_params(split)
            blobs = [self._load_or_build(f, params) for f in recs]
            rates.update({b["recording"]: b["frame_rate"] for b in blobs})
            data = concat_windows(blobs)
            if len(data["window_start"]) == 0:
                raise ValueError(
                    f"{h.name} {split} split (recordings {[f.id for f in recs]}): no window of data.seq_len="
                    f"{h.seq_len} steps (x data.downsample={h.downsample} = "
                    f"{h.seq_len * h.downsample} frames) with >= data.min_agents={h.min_agents} agents: "
                    f"recordings too short or empty"
                    + (f", or data.classes={list(h.classes)} left too few tracks" if h.classes else ""))
            cap = {"train": h.num_train, "val": h.num_val, "test": h.num_test}[split]
            if cap is not None and cap < len(data["window_start"]):
                data = select_windows(data, spread_indices(len(data["window_start"]), cap))
            raw[split] = data
        if h.classes is not None:  # a misspelt class silently selects nothing: say so
            seen = set().union(*(d["class_names"] for d in raw.values()))
            if unknown := sorted(set(h.classes) - seen):
                log.warning("data.classes: %s never occur in %s (classes present: %s)", unknown, h.name,
                            sorted(seen))
        # One downsample factor means one time step only if every recording has the same frame rate.
        if len(set(rates.values())) > 1:
            raise ValueError(f"{h.name}: recordings have different frame rates {rates} (recordingMeta "
                             f"{h.frame_rate_column}); select recordings of one rate with data.recordings")
        self.dt = h.downsample / next(iter(rates.values()))
        try:
            self.normalizer = Normalizer.fit(raw["train"]["states"], raw["train"]["mask"])
        except ValueError as e:  # e.g. only parked vehicles left: a zero velocity range
            raise ValueError(f"{h.name} train split (recordings {raw['train']['recordings']}): cannot fit "
                             f"the normalisation: {e}") from None
        for split, data in raw.items():
            states = fill_absent(self.normalizer.normalize(data["states"]), data["mask"])
            pairs = None
            if split == "test":  # the consistency check reads raw speeds and paths
                vehicle = torch.tensor([c in self.pair_rules.vehicle_classes for c in data["class_names"]])
                pairs = find_pairs(data["states"], data["mask"], data["offsets"],
                                   vehicle[data["agent_class"]], self.pair_rules)
            ds = PackedClipDataset(states, data["mask"], data["offsets"], pairs)
            for key in ("track_id", "agent_class", "class_names", "window_start", "window_recording",
                        "recordings"):
                setattr(ds, key, data[key])
            self.datasets[split] = ds
        log.info("%s windows: %s", h.name, {s: len(d) for s, d in self.datasets.items()})

    def background(self, split: str, index: int) -> tuple[np.ndarray, tuple[float, float, float, float]] | None:
        """The background image of clip ``index`` of ``split`` and its extent (left, right, bottom, top) in
        the tracks' metres, for ``imshow``; None without the image or the recording's ``orthoPxToMeter``.

        A pixel is orthoPxToMeter * background_scale metres (the released images are downscaled) and the
        image's y axis points down while the tracks' points up."""
        h, ds = self.hparams, self.datasets[split]
        files = self.split_recordings()[split][int(ds.window_recording[index])]
        image = files.tracks.parent / h.background_pattern.format(id=files.id)
        if not image.is_file() or "orthoPxToMeter" not in _header(files.recording_meta):
            return None
        meters = float(_read_columns(files.recording_meta, ["orthoPxToMeter"]).iloc[0, 0]) * h.background_scale
        if not (np.isfinite(meters) and meters > 0):
            return None
        pixels = plt_image.imread(image)
        rows, cols = pixels.shape[:2]
        return pixels, (0.0, cols * meters, -rows * meters, 0.0)


LevelXDataModule = InDDataModule  # the same reader serves rounD and uniD


def benchmark_preprocess(tmpdir: str | Path | None = None, minutes: float = 20.0, num_tracks: int = 300,
                         num_parked: int = 20, seed: int = 0) -> float:
    """Seconds to read, validate, downsample and window one synthetic recording of ``minutes`` at 25 Hz
    with ``num_tracks`` tracks (the size of a real inD recording), with the default DNRI settings.

    Writing the CSV files is not timed. No assertion: a measurement to report.
    """
    from dider.data.fakes import write_levelx_recording

    with tempfile.TemporaryDirectory(dir=tmpdir) as tmp:
        frames = int(minutes * 60 * 25)
        # Moving road users stay 20 s to 2 min; parked vehicles the whole recording.
        write_levelx_recording(tmp, 0, num_frames=frames, num_tracks=num_tracks, num_parked=num_parked,
                               seed=seed, min_lifetime=25 * 20, max_lifetime=25 * 120)
        files = discover_recordings(Path(tmp))[0]
        log.info("benchmark: %s, %.0f MB", files.tracks.name, files.tracks.stat().st_size / 2**20)
        t0 = time.perf_counter()
        blob = preprocess_recording(files, WindowParams())
        seconds = time.perf_counter() - t0
        log.info("benchmark: %d tracks -> %d windows, %d agent rows in %.2f s", blob["num_tracks"],
                 len(blob["window_start"]), len(blob["states"]), seconds)
    return seconds
