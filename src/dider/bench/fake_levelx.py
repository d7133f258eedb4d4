"""Synthetic recordings in the exact file format of the levelX data sets (inD, rounD, uniD).

The real recordings may not be redistributed, so the preprocessing benchmark (and the tests) read
recordings generated here: every header column of the levelXdata v1 schema, in the real order, with
consistent metadata (numFrames = finalFrame - initialFrame + 1, trackLifetime = frame -
initialFrame, counts of vehicles / VRUs, frame rate), parked vehicles that never move, VRUs with
width = length = 0, and tracks that enter and leave mid-recording. Nothing here is derived from real
rows.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

TRACKS_COLUMNS = [
    "recordingId", "trackId", "frame", "trackLifetime", "xCenter", "yCenter", "heading", "width",
    "length", "xVelocity", "yVelocity", "xAcceleration", "yAcceleration", "lonVelocity",
    "latVelocity", "lonAcceleration", "latAcceleration",
]
TRACKS_META_COLUMNS = [
    "recordingId", "trackId", "initialFrame", "finalFrame", "numFrames", "width", "length", "class",
]
RECORDING_META_COLUMNS = [
    "recordingId", "locationId", "frameRate", "speedLimit", "weekday", "startTime", "duration",
    "numTracks", "numVehicles", "numVRUs", "latLocation", "lonLocation", "xUtmOrigin", "yUtmOrigin",
    "orthoPxToMeter",
]
VRU_CLASSES = ("pedestrian", "bicycle")
# Typical speed (m/s) and bounding box (width, length; 0 for VRUs as in inD) per class.
_CLASS_SPEED = {"car": 8.0, "truck_bus": 6.0, "bicycle": 4.0, "pedestrian": 1.3}
_CLASS_SIZE = {"car": (1.8, 4.5), "truck_bus": (2.5, 10.0), "bicycle": (0.0, 0.0),
               "pedestrian": (0.0, 0.0)}


def write_levelx_recording(
    root: str | Path,
    recording_id: int,
    num_frames: int = 300,
    num_tracks: int = 8,
    num_parked: int = 2,
    seed: int = 0,
    frame_rate: float = 25.0,
    location_id: int = 1,
    classes: tuple[str, ...] = ("car", "truck_bus", "pedestrian", "bicycle"),
    min_lifetime: int | None = None,
    max_lifetime: int | None = None,
) -> dict[str, Path]:
    """Write ``XX_tracks.csv``, ``XX_tracksMeta.csv``, ``XX_recordingMeta.csv`` for one recording.

    The first ``num_parked`` tracks are parked vehicles present for the whole recording at zero
    speed; the others drive along gently curving paths for a random part of it (between
    ``min_lifetime`` frames, default num_frames // 5, and ``max_lifetime``, default num_frames //
    2). Returns the three paths by kind.
    """
    if num_tracks < num_parked or num_frames < 2:
        raise ValueError(
            "write_levelx_recording: need num_tracks >= num_parked and num_frames >= 2")
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    k = np.arange(num_tracks)
    parked = k < num_parked
    vehicle_classes = [c for c in classes if c not in VRU_CLASSES] or ["car"]
    cls = np.where(parked, np.array(vehicle_classes)[k % len(vehicle_classes)],
                   np.array(classes)[rng.integers(0, len(classes), num_tracks)])

    # Lifetimes and start frames: parked tracks span the recording, the others a random stretch of
    # it.
    lo = min_lifetime or max(2, num_frames // 5)
    hi = max(lo + 1, max_lifetime or num_frames // 2)
    life = np.where(parked, num_frames, rng.integers(lo, hi, num_tracks).clip(max=num_frames))
    initial = np.where(parked, 0, rng.integers(0, num_frames - life + 1))

    speed = np.vectorize(_CLASS_SPEED.get)(cls) * rng.uniform(0.7, 1.3, num_tracks) * ~parked
    yaw_rate = rng.uniform(-0.15, 0.15, num_tracks) * ~parked  # rad/s
    head0 = rng.uniform(0, 2 * np.pi, num_tracks)
    x0, y0 = rng.uniform(20.0, 80.0, num_tracks), rng.uniform(-70.0, -10.0, num_tracks)
    width = np.vectorize(lambda c: _CLASS_SIZE[c][0])(cls)
    length = np.vectorize(lambda c: _CLASS_SIZE[c][1])(cls)

    tracks = _tracks_table(recording_id, life, initial, speed, yaw_rate, head0, x0, y0, width,
                           length, frame_rate)
    meta = pd.DataFrame({
        "recordingId": recording_id, "trackId": k, "initialFrame": initial,
        "finalFrame": initial + life - 1,
        "numFrames": life, "width": width, "length": length, "class": cls,
    })[TRACKS_META_COLUMNS]
    rec = _recording_meta(recording_id, location_id, frame_rate, num_frames, cls)
    name = f"{recording_id:02d}"
    paths = {"tracks": root / f"{name}_tracks.csv", "tracks_meta": root / f"{name}_tracksMeta.csv",
             "recording_meta": root / f"{name}_recordingMeta.csv"}
    tracks.to_csv(paths["tracks"], index=False, float_format="%.5f")
    meta.to_csv(paths["tracks_meta"], index=False, float_format="%.2f")
    rec.to_csv(paths["recording_meta"], index=False)
    return paths


def _tracks_table(recording_id: int, life: np.ndarray, initial: np.ndarray, speed: np.ndarray,
                  yaw_rate: np.ndarray, head0: np.ndarray, x0: np.ndarray, y0: np.ndarray,
                  width: np.ndarray, length: np.ndarray, frame_rate: float) -> pd.DataFrame:
    """``XX_tracks.csv``: one row per (track, frame), tracks contiguous and sorted as in the real
    files, each track driving at its constant speed and yaw rate from its start (per-track arrays
    [K]); all vectorised."""
    track = np.repeat(np.arange(len(life)), life)
    starts = np.concatenate([[0], np.cumsum(life)[:-1]])
    age = np.arange(track.size) - np.repeat(starts, life)
    frame = initial[track] + age
    dt = 1.0 / frame_rate
    head = head0[track] + yaw_rate[track] * age * dt
    v = speed[track]
    vx, vy = v * np.cos(head), v * np.sin(head)
    # Positions integrate the velocities (segmented cumulative sum: subtract each track's running
    # offset).
    cx, cy = np.cumsum(vx * dt), np.cumsum(vy * dt)
    first = np.repeat(starts, life)
    x = x0[track] + cx - cx[first]
    y = y0[track] + cy - cy[first]
    lat_acc = v * yaw_rate[track]  # centripetal
    return pd.DataFrame({
        "recordingId": recording_id, "trackId": track, "frame": frame, "trackLifetime": age,
        "xCenter": x, "yCenter": y, "heading": np.degrees(head) % 360.0, "width": width[track],
        "length": length[track], "xVelocity": vx, "yVelocity": vy,
        "xAcceleration": -lat_acc * np.sin(head), "yAcceleration": lat_acc * np.cos(head),
        "lonVelocity": v, "latVelocity": 0.0, "lonAcceleration": 0.0, "latAcceleration": lat_acc,
    })[TRACKS_COLUMNS]


def _recording_meta(recording_id: int, location_id: int, frame_rate: float, num_frames: int,
                    cls: np.ndarray) -> pd.DataFrame:
    """``XX_recordingMeta.csv``: one row; the fixed fields are a real recording's."""
    num_vru = int(np.isin(cls, VRU_CLASSES).sum())
    return pd.DataFrame([{
        "recordingId": recording_id, "locationId": location_id, "frameRate": frame_rate,
        "speedLimit": 13.89,
        "weekday": "Tuesday", "startTime": 8, "duration": num_frames / frame_rate,
        "numTracks": len(cls), "numVehicles": len(cls) - num_vru, "numVRUs": num_vru,
        "latLocation": 50.782, "lonLocation": 6.071,
        "xUtmOrigin": 293487.5, "yUtmOrigin": 5629711.5, "orthoPxToMeter": 0.0081464,
    }])[RECORDING_META_COLUMNS]
