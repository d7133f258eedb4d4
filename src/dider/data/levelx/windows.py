"""Cutting one levelX recording into windows.

A recording is downsampled on absolute frame numbers (every ``downsample``-th frame from frame 0) and cut
into windows of ``seq_len`` downsampled steps, one every ``stride`` steps. A window keeps the tracks
present in it (at least ``min_agent_steps`` of its steps), ordered by trackId, with a presence mask: agents
enter and leave mid-window. Windows with fewer than ``min_agents`` agents (default 2: a relation needs
two) are dropped (the cut is :func:`dider.data.windowing.cut_windows`, which the table reader uses too).
Windows have different agent counts, so they are stored packed: one row per agent per window, window w owning
rows offsets[w]:offsets[w+1].
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from dider.data.levelx.reading import WindowParams, check_consistency, frame_rate, read_tracks, read_tracks_meta
from dider.data.levelx.recordings import RecordingFiles
from dider.data.windowing import MAX_GRID_CELLS, grid_windows


@dataclass
class RecordingTracks:
    """One recording's rows, downsampled and filtered: track ids [R] int64, downsampled steps [R] int64 and the
    features [R, 4] float32 (x, y, vx, vy), with what the recording's metadata says (every track's id and class,
    the frame rate, the location)."""

    track_id: np.ndarray
    step: np.ndarray
    feats: np.ndarray
    meta_ids: np.ndarray
    meta_class: np.ndarray
    frame_rate: float
    location: int | None
    last_frame: int  # the largest frame read (before downsampling), for messages


def read_recording(files: RecordingFiles, p: WindowParams) -> RecordingTracks:
    """Read and validate one recording's files, downsampled on absolute frame numbers (DNRI's feats[::10] from
    frame 0), the tracks of filtered classes dropped."""
    tid, frame, feats = read_tracks(files, p)
    meta_ids, meta_frames, meta_class = read_tracks_meta(files, p)
    rate, location = frame_rate(files, p)
    check_consistency(files, tid, frame, meta_ids, meta_frames)
    keep = frame % p.downsample == 0
    if p.classes is not None:
        keep &= np.isin(tid, meta_ids[np.isin(meta_class, p.classes)])
    return RecordingTracks(tid[keep], frame[keep] // p.downsample, feats[keep], meta_ids, meta_class, rate, location,
                           int(frame.max()) if frame.size else 0)


def preprocess_recording(files: RecordingFiles, p: WindowParams) -> dict[str, Any]:
    """Read and validate one recording and cut its windows (raw units, packed).

    Returns a dict of: states [P, T, 4] float32 (zeros where absent), mask [P, T] bool, offsets [W+1]
    long (window w owns rows offsets[w]:offsets[w+1], agents by trackId), track_id [P] long,
    agent_class [P] long (index into class_names), class_names list[str], window_start [W] long
    (downsampled step), frame_rate, location_id, recording, num_steps (downsampled), num_tracks.
    """
    return cut_recording(read_recording(files, p), p, files)


def cut_recording(r: RecordingTracks, p: WindowParams, files: RecordingFiles) -> dict[str, Any]:
    """One recording's windows (:func:`preprocess_recording`'s dict) from its rows."""
    tid, step, feats, meta_ids, meta_class = r.track_id, r.step, r.feats, r.meta_ids, r.meta_class
    class_names = sorted(set(meta_class.tolist()))
    out = _empty_windows(p, class_names, r.frame_rate, r.location, files.id)
    if tid.size == 0:
        return out

    # Dense grid of the recording: [S steps, K tracks]. Column order = sorted trackId = agent order.
    tracks, k = np.unique(tid, return_inverse=True)
    num_steps = int(step.max()) + 1
    if num_steps * tracks.size > MAX_GRID_CELLS:
        raise ValueError(f"{files.tracks}: column {p.frame_column!r} reaches frame {r.last_frame}: "
                         f"{num_steps} steps x {tracks.size} tracks is implausibly large for one recording")
    grid = np.zeros((num_steps, tracks.size, 4), np.float32)
    present = np.zeros((num_steps, tracks.size), bool)
    grid[step, k] = feats
    present[step, k] = True
    out["num_steps"], out["num_tracks"] = num_steps, int(tracks.size)

    states, mask, counts, starts, a = grid_windows(grid, present, p.seq_len, p.stride, p.min_agent_steps,
                                                   p.min_agents, p.max_agents)
    if starts.size == 0:
        return out
    offsets = np.zeros(len(starts) + 1, np.int64)
    offsets[1:] = np.cumsum(counts)
    code = np.searchsorted(class_names, meta_class[np.searchsorted(meta_ids, tracks)])
    out.update(
        states=torch.from_numpy(states),
        mask=torch.from_numpy(mask),
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
