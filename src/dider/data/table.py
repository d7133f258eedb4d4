"""Cutting a table of long tracks into windows: a ``.csv`` or ``.parquet`` table (``data.source.path``), one row per
agent per frame, or what a track format reads into the same rows (:mod:`dider.data.track_sources`: a
:class:`~dider.data.track_sources.TrackFile`, e.g. ETH/UCY text files; a soccer provider's tracking data through
kloppy), as the scenes of :class:`~dider.data.tracks.TracksDataModule`, which splits and serves the windows.

A table's columns are named in ``data.source.columns``: ``agent``, ``frame`` (integer frame numbers), ``x``, ``y``
(required), ``scene`` (null: a column called ``scene`` if the file has one, else the whole file is one scene),
``vx``/``vy`` (null: finite differences, both or neither), ``agent_class`` (optional, one class per agent). Extra
columns are ignored. Scene and agent ids may be integers (kept as they are) or strings (coded; the names are in
``source_names``); an agent is a (scene, agent id) pair.

Cutting (the ``data.windows`` node, :class:`~dider.data.windowing.Windows`): each scene is downsampled to every
``downsample``-th frame counted from the scene's first frame, and laid on a grid of steps x agents: a frame missing
inside an agent's span is an absent step (mask False). Without velocity columns, v[t] = (pos[t] - pos[t-1]) *
frame_rate / downsample needs the agent at both steps, and the scene's first step is dropped (as the npz reader
does). A step whose speed exceeds ``max_speed`` (data units per second) is a jump of the tracking (an id switch, a
track re-acquired), not motion: the agent is absent there, so the track breaks instead of feeding an impossible
velocity to the model and to the normalisation's range. Windows of ``seq_len`` steps start every ``stride`` steps of
a scene; a window keeps the agents present in >= ``min_agent_steps`` of its steps (ordered by id) and is dropped with
fewer than ``min_agents``. A window's ``frame`` is the table's frame of its step 0. Positions are held relative
to the table's centre (subtracted in float64 before the windows' one float32 rounding, so coordinates of any size,
UTM's 5e6 m included, keep their precision; a trained model keeps its origin, and predictions add it back). Bad
input raises before any windowing, naming the file, the column and the CSV line (parquet: the row).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dider.data.packed import PackedWindows, join
from dider.data.table_reading import id_name
from dider.data.windowing import MAX_GRID_CELLS, Windows, grid_windows, midpoint

log = logging.getLogger(__name__)


def scene_grid(xy: np.ndarray, vel: np.ndarray | None, step: np.ndarray, agent: np.ndarray,
               rate: float) -> tuple[np.ndarray, np.ndarray]:
    """One scene's rows on a dense steps x agents grid.

    xy: [r, 2], vel: [r, 2] or None, step, agent: [r] int64 (grid coordinates) -> grid [S, K, 4] float64
    (x, y, vx, vy; zeros where absent) and present [S, K] bool. Without ``vel`` the velocities are finite
    differences scaled by ``rate`` (frame_rate / downsample) and S is one step shorter: the first step,
    which has no predecessor, is dropped.
    """
    num_steps, k = int(step.max()) + 1, int(agent.max()) + 1
    grid = np.zeros((num_steps, k, 4))
    present = np.zeros((num_steps, k), bool)
    grid[step, agent, :2] = xy
    present[step, agent] = True
    if vel is not None:
        grid[step, agent, 2:] = vel
        return grid, present
    # Differences in float64, before the origin is subtracted and the windows are cast to float32.
    grid[1:, :, 2:] = (grid[1:, :, :2] - grid[:-1, :, :2]) * rate
    both = present[1:] & present[:-1]  # a velocity needs the agent at both ends of the step
    return grid[1:] * both[..., None], both


def drop_jumps(grid: np.ndarray, present: np.ndarray, max_speed: float | None) -> tuple[np.ndarray, np.ndarray, int]:
    """Mark the steps faster than ``max_speed`` absent: grid [S, K, 4], present [S, K] -> the same and the
    number of steps dropped."""
    if max_speed is None:
        return grid, present, 0
    fast = present & (np.hypot(grid[..., 2], grid[..., 3]) > max_speed)
    return grid * ~fast[..., None], present & ~fast, int(fast.sum())


def _too_few_frames(path: Path | str, seq_len: int, downsample: int, drop: int, longest: int) -> str:
    """The arithmetic of a window that no scene is long enough for (``drop``: the step finite differences use)."""
    need = (seq_len + drop - 1) * downsample + 1
    shortest = Windows.MIN_SEQ_LEN
    fix = (f"set data.windows.seq_len <= {longest}" if longest >= shortest
           else f"no scene is long enough for the shortest window (data.windows.seq_len={shortest})")
    return (f"{path}: too few frames for one window of data.windows.seq_len={seq_len} steps: a window needs "
            f"{seq_len} step(s){' + 1 for the finite-difference velocities' if drop else ''} of "
            f"data.windows.downsample={downsample} frame(s), i.e. a scene spanning >= {need} frames, and the longest "
            f"scene has {longest + drop} step(s): {fix}"
            + (", or lower data.windows.downsample" if downsample > 1 else ""))


def table_windows(t: dict[str, Any], path: Path | str, frame_rate: float, w: Windows, scenes: Sequence[int],
                  stride: int, origin: tuple[float, float] = (0.0, 0.0)) -> PackedWindows:
    """Cut the ``scenes`` (indices, in order) of a read table (:func:`~dider.data.table_reading.read_table`'s dict;
    ``path`` names it in messages) into packed windows (raw units: positions less ``origin``) starting every
    ``stride`` steps: a cut of :class:`~dider.data.tracks.Tracks`. Steps faster than ``w.max_speed`` are absent (a
    warning counts them)."""
    lo_hi, first_frame, keep, step, hint = _scene_steps(t, path, w.downsample)
    drop = 1 if t["vel"] is None else 0
    parts: list[PackedWindows] = []
    longest = steps_kept = steps_fast = 0
    names = t["names"].get("agent_class")
    for z in scenes:  # scenes: dense grids of different sizes
        lo, hi = lo_hi[z]
        rows = lo + np.flatnonzero(keep[lo:hi])
        ids, first, local = np.unique(t["agent"][rows], return_index=True, return_inverse=True)
        if (int(step[rows].max()) + 1) * ids.size > MAX_GRID_CELLS:
            scene, span = id_name(t, "scene", t["scene_ids"][z]), int(step[rows].max()) + 1
            raise ValueError(f"{path}: scene {scene} spans {span} steps x {ids.size} agents: implausibly large (is "
                             f"data.windows.downsample={w.downsample} right?)")
        grid, present = scene_grid(t["xy"][rows], None if drop else t["vel"][rows], step[rows], local,
                                   frame_rate / w.downsample)
        grid, present, fast = drop_jumps(grid, present, w.max_speed)
        steps_kept, steps_fast = steps_kept + int(present.sum()), steps_fast + fast
        longest = max(longest, present.shape[0])
        states, mask, counts, starts, agent = grid_windows(grid, present, w.seq_len, stride, w.min_agent_steps,
                                                           w.min_agents, w.max_agents, origin)
        parts.append(PackedWindows(
            torch.from_numpy(states), torch.from_numpy(mask),
            torch.from_numpy(np.concatenate([[0], np.cumsum(counts)])), torch.from_numpy(ids[agent]),
            torch.from_numpy(starts), torch.from_numpy(np.full(len(starts), z)),
            torch.from_numpy(first_frame[z] + (starts + drop) * w.downsample),
            None if names is None else torch.from_numpy(t["agent_class"][rows][first][agent]), names))
    if steps_fast:
        log.warning("%s: %d of %d agent-steps (%.2f%%) move faster than data.windows.max_speed=%s per second: "
                    "tracking jumps, marked absent", path, steps_fast, steps_kept + steps_fast,
                    100 * steps_fast / (steps_kept + steps_fast), w.max_speed)
    if longest < w.seq_len:
        raise ValueError(_too_few_frames(path, w.seq_len, w.downsample, drop, longest))
    if not sum(len(p) for p in parts):
        raise ValueError(f"{path}: no window of data.windows.seq_len={w.seq_len} steps has >= "
                         f"data.windows.min_agents={w.min_agents} agents present in >= "
                         f"data.windows.min_agent_steps={w.min_agent_steps} of its steps{hint}")
    return join(parts, w.seq_len)


def _scene_steps(t: dict[str, Any], path: Path | str, downsample: int
                 ) -> tuple[list[tuple[int, int]], np.ndarray, np.ndarray, np.ndarray, str]:
    """Each scene's row range, its first frame [Z], which rows fall on a kept step [R] bool, their step [R] and a
    hint for the messages when the frames step by more than one (a warning names it)."""
    bounds = np.flatnonzero(np.diff(t["scene"])) + 1
    lo_hi = list(zip([0, *bounds.tolist()], [*bounds.tolist(), len(t["scene"])], strict=True))
    first_frame = np.minimum.reduceat(t["frame"], np.array([lo for lo, _ in lo_hi]))  # [Z]
    offset = t["frame"] - first_frame[t["scene"]]
    keep = offset % downsample == 0
    step = offset // downsample
    hint = ""
    if (gap := int(np.gcd.reduce(step[keep]))) > 1:  # e.g. frames numbered 0, 10, 20 with downsample=1
        hint = f" (frames step by {gap * downsample}: set data.windows.downsample={gap * downsample}?)"
        log.warning("%s: %d of every %d steps are absent%s", path, gap - 1, gap, hint)
    return lo_hi, first_frame, keep, step, hint


class TableTracks:
    """A table's scenes (:class:`~dider.data.tracks.Tracks`), read on first use by ``read`` (the source's rows and
    their frame rate); ``where()`` names the input in messages (once read: a source's settings are checked as it
    reads)."""

    def __init__(self, read: Callable[[], tuple[dict[str, Any], float]], where: Callable[[], str],
                 windows: Windows) -> None:
        self._read, self.where, self.windows = read, where, windows
        self._rows: tuple[dict[str, Any], float] | None = None

    def _loaded(self) -> tuple[dict[str, Any], float]:
        if self._rows is None:
            self._rows = self._read()
        return self._rows

    @property
    def table(self) -> dict[str, Any]:
        """The rows (:func:`~dider.data.table_reading.read_table`'s dict), read on first use."""
        return self._loaded()[0]

    @property
    def frame_rate(self) -> float:
        """Frames per second of the frame column: the source's, or what it read (a soccer provider's)."""
        return self._loaded()[1]

    @property
    def scenes(self) -> list[str]:
        """The scenes' names, in id order."""
        names = self.names.get("scene")
        return [str(i) if names is None else names[i] for i in self.table["scene_ids"].tolist()]

    @property
    def origin(self) -> tuple[float, float]:
        """The centre of the table's positions (float64): what its windows are relative to when cut for training."""
        return midpoint(self.table["xy"])

    @property
    def scene_ids(self) -> torch.Tensor:
        """[Z] long: the scene column's ids (or codes into ``names["scene"]``); [0] without one."""
        return torch.from_numpy(self.table["scene_ids"])

    @property
    def names(self) -> dict[str, list[str]]:
        """The names of string ids: scene, agent, agent_class."""
        return self.table["names"]

    @property
    def has_scene(self) -> bool:
        return self.table["has_scene"]

    @property
    def has_classes(self) -> bool:
        return self.table["agent_class"] is not None

    def cut(self, groups: Mapping[str, tuple[Sequence[int], int]],
            origin: tuple[float, float]) -> dict[str, PackedWindows]:
        """group -> (scene indices, stride) to the group's windows (:func:`table_windows`), relative to ``origin``."""
        return {group: table_windows(self.table, self.where(), self.frame_rate, self.windows, scenes, stride, origin)
                for group, (scenes, stride) in groups.items()}
