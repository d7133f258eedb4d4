"""A levelX data set's recordings as scenes (:class:`~dider.data.tracks.Tracks`): found in recording order, each read,
validated and cut once per window setting and cached under ``cache_dir/levelx/``, keyed by the source files' sizes
and modification times and by every parameter that changes the windows, so runs with the same settings share it and
a changed file is re-read (written atomically: a killed run leaves no half-written file)."""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib.image as plt_image
import numpy as np
import torch

from dider.data.cache import cache_key, load_or_build
from dider.data.columns import csv_header, read_columns
from dider.data.levelx.reading import WindowParams
from dider.data.levelx.recordings import RecordingFiles, discover_recordings
from dider.data.levelx.windows import preprocess_recording
from dider.data.packed import PackedWindows, join
from dider.data.windowing import Windows

if TYPE_CHECKING:
    from dider.data.levelx.source import LevelXSource

log = logging.getLogger(__name__)

CACHE_VERSION = 1  # part of the cache key: bump it when preprocessing changes what a cached file holds


class LevelXTracks:
    """The recordings of ``source`` (found on first use), cut by ``windows``, cached under ``cache_dir``."""

    has_scene = True
    has_classes = True  # tracksMeta's class column

    def __init__(self, source: LevelXSource, windows: Windows, cache_dir: Path) -> None:
        self.source, self.windows, self.cache_dir = source, windows, cache_dir
        self._files: list[RecordingFiles] | None = None
        self.frame_rate: float | None = None  # known once cut
        self.names: dict[str, list[str]] = {}
        # each recording's background image, read once: the figures draw many clips of one recording
        self._backgrounds: dict[int, tuple[np.ndarray, tuple[float, float, float, float]]] = {}

    @property
    def files(self) -> list[RecordingFiles]:
        """The recordings, in recording order (all found, or ``data.source.recordings``)."""
        if self._files is None:
            s, f = self.source, self.source.files
            if s.root is None:
                raise ValueError(f"data.source.root is not set: point it at the folder with the {s.name} recordings "
                                 f"({f.tracks.format(id='XX')}, ...)")
            self._files = discover_recordings(Path(s.root).expanduser(), f.tracks, f.tracks_meta, f.recording_meta,
                                              s.recordings)
            if not all(r.id.isdigit() for r in self._files):  # names for ids that are not numbers
                self.names["scene"] = [r.id for r in self._files]
        return self._files

    @property
    def scenes(self) -> list[str]:
        return [r.id for r in self.files]

    @property
    def scene_ids(self) -> torch.Tensor:
        """Recording ids as source scene ids: the number itself for numeric ids ("07" -> 7), else the position in
        ``names["scene"]``."""
        scenes = self.scenes  # found first: finding them names ids that are not numbers
        numeric = "scene" not in self.names
        return torch.tensor([int(r) if numeric else i for i, r in enumerate(scenes)], dtype=torch.long)

    def params(self, stride: int) -> WindowParams:
        """What changes a recording's windows (its cache key: the field names are the cache's)."""
        c, w, classes = self.source.columns, self.windows, self.source.classes
        return WindowParams(
            track_id_column=c.track_id, frame_column=c.frame, class_column=c.agent_class,
            frame_rate_column=c.frame_rate, features=tuple(c.features),
            classes=None if classes is None else tuple(sorted(classes)), downsample=w.downsample, seq_len=w.seq_len,
            stride=stride, min_agent_steps=w.min_agent_steps, min_agents=w.min_agents, max_agents=w.max_agents)

    def cache_path(self, files: RecordingFiles, params: WindowParams) -> Path:
        key = cache_key({"version": CACHE_VERSION, "recording": files.id, "files": files.signature(),
                         "params": asdict(params)})
        return self.cache_dir / "levelx" / f"{self.source.name}_{files.id}_{key}.pt"

    def recording(self, files: RecordingFiles, params: WindowParams) -> dict[str, Any]:
        """One recording's windows (:func:`~dider.data.levelx.windows.preprocess_recording`), cached."""
        path = self.cache_path(files, params)

        def build() -> dict[str, Any]:
            t0 = time.perf_counter()
            blob = preprocess_recording(files, params)
            log.info("%s recording %s: %d windows from %d tracks in %.1f s -> %s", self.source.name, files.id,
                     len(blob["window_start"]), blob["num_tracks"], time.perf_counter() - t0, path)
            return blob

        return load_or_build(path, build)

    def prepare(self, groups: Mapping[str, tuple[Sequence[int], int]]) -> None:
        """Read, validate and cache every recording of the groups not cached yet."""
        for scenes, stride in groups.values():
            params = self.params(stride)
            for i in scenes:
                if not self.cache_path(self.files[i], params).exists():
                    self.recording(self.files[i], params)

    # A levelX recording's positions are metres from its own local origin (its UTM origin is in its metadata):
    # small numbers, which the reader reads as float32.
    origin = (0.0, 0.0)

    def cut(self, groups: Mapping[str, tuple[Sequence[int], int]],
            origin: tuple[float, float]) -> dict[str, PackedWindows]:
        """Each group's windows, relative to ``origin`` (a trained model's); every recording must run at one frame
        rate (one downsample factor, one step)."""
        out, rates, seen = {}, {}, set()
        w, classes = self.windows, self.source.classes
        for group, (scenes, stride) in groups.items():
            params = self.params(stride)
            blobs = [self.recording(self.files[i], params) for i in scenes]
            rates.update({b["recording"]: b["frame_rate"] for b in blobs})
            seen.update(*(b["class_names"] for b in blobs))
            out[group] = join([_part(b, i, w.downsample) for b, i in zip(blobs, scenes, strict=True)], w.seq_len)
            if len(out[group]) == 0:
                raise ValueError(
                    f"{self.source.name} {group} split (recordings {[self.files[i].id for i in scenes]}): no window "
                    f"of data.windows.seq_len={w.seq_len} steps (x data.windows.downsample={w.downsample} = "
                    f"{w.seq_len * w.downsample} frames) with >= data.windows.min_agents={w.min_agents} agents: "
                    f"recordings too short or empty"
                    + (f", or data.source.classes={list(classes)} left too few tracks" if classes else ""))
        if classes is not None and (unknown := sorted(set(classes) - seen)):  # a misspelt class selects nothing
            log.warning("data.source.classes: %s never occur in %s (classes present: %s)", unknown, self.source.name,
                        sorted(seen))
        if len(set(rates.values())) > 1:
            raise ValueError(f"{self.source.name}: recordings have different frame rates {rates} (recordingMeta "
                             f"{self.source.columns.frame_rate}); select recordings of one rate with "
                             f"data.source.recordings")
        self.frame_rate = next(iter(rates.values()))
        return {group: windows.shifted(origin) for group, windows in out.items()}

    def background(self, scene: int) -> tuple[np.ndarray, tuple[float, float, float, float]] | None:
        """The background image of recording ``scene`` and its extent (left, right, bottom, top) in the tracks'
        metres, for ``imshow``; None without the image or the recording's ``orthoPxToMeter``.

        A pixel is orthoPxToMeter * background_scale metres (the released images are downscaled) and the image's y
        axis points down while the tracks' points up."""
        if scene not in self._backgrounds and (found := self._read_background(scene)) is not None:
            self._backgrounds[scene] = found
        return self._backgrounds.get(scene)

    def _read_background(self, scene: int) -> tuple[np.ndarray, tuple[float, float, float, float]] | None:
        files = self.files[scene]
        image = files.tracks.parent / self.source.files.background.format(id=files.id)
        if not image.is_file() or "orthoPxToMeter" not in csv_header(files.recording_meta):
            return None
        meters = float(read_columns(files.recording_meta, ["orthoPxToMeter"]).iloc[0, 0]) * self.source.background_scale
        if not (np.isfinite(meters) and meters > 0):
            return None
        try:
            pixels = plt_image.imread(image)
        except Exception as e:  # an optional extra (PIL raises SyntaxError for a damaged PNG): never lose a run
            log.warning("%s: cannot read the background image (%s: %s); drawing without it", image,
                        type(e).__name__, e)
            return None
        rows, cols = pixels.shape[:2]
        return pixels, (0.0, cols * meters, -rows * meters, 0.0)


def _part(blob: dict[str, Any], scene: int, downsample: int) -> PackedWindows:
    """A recording's cached windows (the cache file's dict) as a part of a cut (:func:`~dider.data.packed.join`):
    steps anchored at frame 0."""
    start = blob["window_start"]
    return PackedWindows(blob["states"], blob["mask"], blob["offsets"], blob["track_id"], start,
                         torch.full((len(start),), scene, dtype=torch.long), start * downsample, blob["agent_class"],
                         blob["class_names"])
