"""Data sets of long tracks: a ``.csv`` or ``.parquet`` table (``data.source.path``), one row per agent per frame, or
what a reader reads into the same rows (``data.source.reader``: :mod:`dider.data.track_sources`, e.g. ETH/UCY text
files, a soccer provider's tracking data through kloppy).

A table's columns are named in ``data.source.columns``: ``agent``, ``frame`` (integer frame numbers), ``x``, ``y``
(required), ``scene`` (null: a column called ``scene`` if the file has one, else the whole file is one scene),
``vx``/``vy`` (null: finite differences, both or neither), ``agent_class`` (optional, one class per agent). Extra
columns are ignored. Scene and agent ids may be integers (kept as they are) or strings (coded; the names are in
``source_names``); an agent is a (scene, agent id) pair.

Cutting (the ``data.windows`` node, :class:`~dider.data.windowing.Windows`): each scene is downsampled to every
``downsample``-th frame counted from the scene's first frame, and laid
on a grid of steps x agents: a frame missing inside an agent's span is an absent step (mask False).
Without velocity columns, v[t] = (pos[t] - pos[t-1]) * frame_rate / downsample needs the agent at both
steps, and the scene's first step is dropped (as the npz reader does). A step whose speed exceeds
``max_speed`` (data units per second) is a jump of the tracking (an id switch, a track re-acquired), not
motion: the agent is absent there, so the track breaks instead of feeding an impossible velocity to the model
and to the normalisation's range. Windows of ``seq_len`` steps start
every ``stride`` steps of a scene; a window keeps the agents present in >= ``min_agent_steps`` of its steps
(ordered by id) and is dropped with fewer than ``min_agents``. Windows have different agent counts, so
they are stored packed and padded per batch (:class:`~dider.data.common.PackedClipDataset`).

Source ids (:mod:`dider.data.common`): ``clip`` the window's number in reading order (scenes in order of
first appearance, then time), ``scene``, ``frame`` (the table's frame of the window's step 0) and
``agent``. The split is by scene with >= 3 scenes that have windows (no window of a test scene is
trained on), else by window. Bad input raises before any windowing, naming the file, the column and the
CSV line (parquet: the row).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from dider.data.batch import Normalizer
from dider.data.clip_splits import fractions_problem, split_indices
from dider.data.common import (
    SPLITS,
    BaseDataModule,
    PackedClipDataset,
    pad_collate,
    ragged_rows,
    spread_indices,
)
from dider.data.table_reading import id_name
from dider.data.track_sources import track_source
from dider.data.windowing import MAX_GRID_CELLS, Windows, grid_windows
from dider.protocol import fill_absent
from dider.validation import Rule, check_settings

log = logging.getLogger(__name__)

# -- windows


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
    # Differences in float64 before the float32 cast: large coordinates (e.g. UTM) keep their precision.
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
    return (f"{path}: too few frames for one window of data.windows.seq_len={seq_len} steps: a window needs "
            f"{seq_len} step(s){' + 1 for the finite-difference velocities' if drop else ''} of "
            f"data.windows.downsample={downsample} frame(s), i.e. a scene spanning >= {need} frames, and the longest "
            f"scene has {longest + drop} step(s): set data.windows.seq_len <= {longest}"
            + (", or lower data.windows.downsample" if downsample > 1 else ""))


def table_windows(t: dict[str, Any], path: Path | str, frame_rate: float, downsample: int, seq_len: int,
                  stride: int, min_agent_steps: int, min_agents: int, max_speed: float | None = None,
                  max_agents: int | None = None) -> dict[str, Any]:
    """Cut every scene of a read table (:func:`~dider.data.table_reading.read_table`'s dict; ``path`` names
    it in messages) into packed windows (raw units), in reading order; steps faster than ``max_speed`` are
    absent (a warning counts them).

    Returns states [P, T, 4] float32 (zeros where absent), mask [P, T] bool, offsets [W+1] long (window w
    owns rows offsets[w]:offsets[w+1]), agent [P] long (ids or codes), agent_class [P] long or None, clip,
    scene, frame [W] long (source ids), scene_index [W] long (the scene's reading-order index), names and
    has_scene.
    """
    lo_hi, first_frame, keep, step, hint = _scene_steps(t, path, downsample)
    drop = 1 if t["vel"] is None else 0
    parts: list[dict[str, np.ndarray]] = []
    longest = steps_kept = steps_fast = 0
    for z, (lo, hi) in enumerate(lo_hi):  # scenes: dense grids of different sizes
        rows = lo + np.flatnonzero(keep[lo:hi])
        ids, first, local = np.unique(t["agent"][rows], return_index=True, return_inverse=True)
        if (int(step[rows].max()) + 1) * ids.size > MAX_GRID_CELLS:
            scene, span = id_name(t, "scene", t["scene_ids"][z]), int(step[rows].max()) + 1
            raise ValueError(f"{path}: scene {scene} spans {span} steps x {ids.size} agents: implausibly large (is "
                             f"data.windows.downsample={downsample} right?)")
        grid, present = scene_grid(t["xy"][rows], None if drop else t["vel"][rows], step[rows], local,
                                   frame_rate / downsample)
        grid, present, fast = drop_jumps(grid, present, max_speed)
        steps_kept, steps_fast = steps_kept + int(present.sum()), steps_fast + fast
        longest = max(longest, present.shape[0])
        states, mask, counts, starts, agent = grid_windows(grid, present, seq_len, stride, min_agent_steps,
                                                           min_agents, max_agents)
        parts.append({
            "states": states, "mask": mask, "counts": counts, "agent": ids[agent],
            "agent_class": None if t["agent_class"] is None else t["agent_class"][rows][first][agent],
            "scene_index": np.full(len(starts), z), "frame": first_frame[z] + (starts + drop) * downsample,
        })
    if steps_fast:
        log.warning("%s: %d of %d agent-steps (%.2f%%) move faster than data.windows.max_speed=%s per second: "
                    "tracking jumps, marked absent", path, steps_fast, steps_kept + steps_fast,
                    100 * steps_fast / (steps_kept + steps_fast), max_speed)
    if longest < seq_len:
        raise ValueError(_too_few_frames(path, seq_len, downsample, drop, longest))
    if not sum(len(p["frame"]) for p in parts):
        raise ValueError(f"{path}: no window of data.windows.seq_len={seq_len} steps has >= "
                         f"data.windows.min_agents={min_agents} agents present in >= "
                         f"data.windows.min_agent_steps={min_agent_steps} of its steps{hint}")
    return _packed(parts, t)


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


def _packed(parts: list[dict[str, np.ndarray]], t: dict[str, Any]) -> dict[str, Any]:
    """The scenes' windows (one part per scene) concatenated in reading order: :func:`table_windows`' dict."""
    out = {k: torch.from_numpy(np.concatenate([p[k] for p in parts]))
           for k in ("states", "mask", "agent", "scene_index", "frame")}
    counts = torch.from_numpy(np.concatenate([p["counts"] for p in parts]))
    out["offsets"] = torch.cat([torch.zeros(1, dtype=torch.long), counts.cumsum(0)])
    out["agent_class"] = None if t["agent_class"] is None else torch.from_numpy(
        np.concatenate([p["agent_class"] for p in parts]))
    out["clip"] = torch.arange(len(out["frame"]))
    out["scene"] = torch.from_numpy(t["scene_ids"])[out["scene_index"]]
    out["names"], out["has_scene"] = t["names"], t["has_scene"]
    return out


class TableDataModule(BaseDataModule):
    """Windows of a data set of long tracks: a table, or what a reader reads (see the module docstring).

    Batches: states [B, T, N, 4] (normalised; zeros for absent agents), mask [B, T, N] bool and source
    (clip, scene, frame [B], agent [B, N]); N is the largest agent count in the batch. After ``setup``:
    ``normalizer``, ``datasets`` (PackedClipDataset per split, with ``agent_class`` [P] and ``class_names``
    when the table has a class column), ``source_names``, ``dt`` (seconds per step) and ``frame_step``
    (table frames per step). ``cache_dir`` is accepted for a uniform interface; nothing is cached.
    """

    predicts = True

    collate_fn = staticmethod(pad_collate)
    WINDOWS = Windows()  # this data set's window defaults; data.windows overrides them key by key
    # the window settings the table's cut does not read
    UNUSED = {"eval_stride": "a table is cut before its split: data.windows.stride serves every split"}

    SETTINGS: ClassVar[dict[str, Rule | type]] = BaseDataModule.SETTINGS | {
        "windows": Windows, "split": fractions_problem}

    def __init__(
        self,
        source: Mapping[str, Any] | None = None,
        windows: Mapping[str, Any] | None = None,
        split: Sequence[float] = (0.8, 0.1, 0.1),
        seed: int = 1,
        num_train: int | None = None,
        num_val: int | None = None,
        num_test: int | None = None,
        loader: Mapping[str, Any] | None = None,
        cache_dir: str | None = None,
    ) -> None:
        """source: what is read (:mod:`dider.data.track_sources`): ``reader`` (``table``: the file's columns named
        in ``columns``; ``kloppy``: a soccer provider's files; or a format's reader of :mod:`dider.data.readers`,
        e.g. ``eth_ucy``, a folder of ETH/UCY text files), ``path`` and ``frame_rate`` (frames per second of the
        frame column: differenced velocities are per second).
        windows: how scenes are cut (:class:`~dider.data.windowing.Windows`): ``seq_len`` steps, a window every
        ``stride`` steps of a scene (null: seq_len, no overlap), ``downsample``, ``min_agent_steps``,
        ``min_agents``; ``max_speed``: a step faster than this (data units per second) is a tracking jump, the
        agent absent there (null keeps every step).
        split: train / val / test fractions: of the scenes with >= 3 scenes, else of the windows.
        seed: the split seed."""
        super().__init__()
        check_settings(self, locals(), key="data")
        self.source = track_source(source)
        self.windows = Windows.of(self.WINDOWS, windows, self.UNUSED)
        self.save_hyperparameters(logger=False)
        self.hparams["source"], self.hparams["windows"] = asdict(self.source), asdict(self.windows)  # as read
        self.init_shared()
        self.units = self.source.UNITS
        self.frame_step = self.windows.downsample
        self.dt = None if self.source.frame_rate is None else self.windows.downsample / self.source.frame_rate
        self._rows: tuple[dict[str, Any], float] | None = None

    def _read(self) -> dict[str, Any]:
        """The source's rows (:func:`~dider.data.table_reading.read_table`'s dict), read once; a source that
        finds its own frame rate (a soccer provider's) records it, so that the checkpoint carries it."""
        if self._rows is None:
            self._rows = self.source.rows()
            rate = self._rows[1]
            if self.source.frame_rate is None:
                self.source = replace(self.source, frame_rate=rate)
                self.hparams["source"] = asdict(self.source)
                self.dt = self.windows.downsample / rate
        return self._rows[0]

    def _source(self) -> str:
        """What messages name as the data's origin."""
        return self.source.where()

    def _windows(self) -> dict[str, Any]:
        rows, w = self._read(), self.windows  # first: reading may fix the frame rate the velocities use
        data = table_windows(rows, self._source(), self.source.frame_rate, w.downsample, w.seq_len,
                             w.stride or w.seq_len, w.min_agent_steps, w.min_agents, w.max_speed, w.max_agents)
        self.source_names = {k: v for k, v in data["names"].items() if k in ("scene", "agent")}
        return data

    def _dataset(self, data: dict[str, Any], idx: torch.Tensor, normalizer: Normalizer) -> PackedClipDataset:
        """The windows ``idx`` [K] long, normalised, with their source ids."""
        rows, offsets = ragged_rows(data["offsets"], idx)
        mask = data["mask"][rows]
        states = fill_absent(normalizer.normalize(data["states"][rows]), mask)
        keys = ("clip", "scene", "frame") if data["has_scene"] else ("clip", "frame")
        ds = PackedClipDataset(states, mask, offsets, sources={k: data[k][idx] for k in keys},
                               agent_ids=data["agent"][rows])
        if data["agent_class"] is not None:
            ds.agent_class, ds.class_names = data["agent_class"][rows], data["names"]["agent_class"]
        return ds

    def _split(self, data: dict[str, Any]) -> tuple[dict[str, torch.Tensor], str]:
        """Window indices of each split, by scene when >= 3 scenes have windows, else by window."""
        h = self.hparams
        scenes = torch.unique(data["scene_index"])
        by = "scene" if len(scenes) >= 3 else "window"
        try:
            parts = split_indices(len(scenes) if by == "scene" else len(data["clip"]), h.split, h.seed)
        except ValueError as e:
            raise ValueError(f"{self._source()}: {len(data['clip'])} windows: {e}") from None
        if by == "scene":
            parts = {s: torch.isin(data["scene_index"], scenes[p]).nonzero().squeeze(1) for s, p in parts.items()}
        caps = {"train": h.num_train, "val": h.num_val, "test": h.num_test}
        return {s: idx[spread_indices(len(idx), caps[s])] for s, idx in parts.items()}, by

    def setup(self, stage: str | None = None) -> None:
        if stage == "predict":  # every window, no split, the trained model's normalisation
            if "predict" not in self.datasets:
                normalizer = self.predict_normalizer(self._source())
                data = self._windows()
                self.datasets["predict"] = self._dataset(data, data["clip"], normalizer)
            return
        if all(s in self.datasets for s in SPLITS):
            return
        data = self._windows()
        parts, by = self._split(data)
        rows, _ = ragged_rows(data["offsets"], parts["train"])
        try:
            self.normalizer = self.train_normalizer(lambda: Normalizer.fit(data["states"][rows], data["mask"][rows]))
        except ValueError as e:  # e.g. agents that never move: a zero velocity range
            raise ValueError(f"{self._source()}: cannot fit the normalisation on the train split: {e}") from None
        for split, idx in parts.items():
            self.datasets[split] = self._dataset(data, idx, self.normalizer)
        log.info("%s: %d windows from %d scenes, split by %s: %s", self._source(), len(data["clip"]),
                 len(torch.unique(data["scene_index"])), by, {s: len(d) for s, d in self.datasets.items()})
        if by == "window" and (self.windows.stride or self.windows.seq_len) < self.windows.seq_len:
            log.warning("data.windows.stride=%d < data.windows.seq_len=%d with a split by window: val / test windows "
                        "share steps with training windows", self.windows.stride, self.windows.seq_len)
