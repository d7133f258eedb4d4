"""inD (and rounD / uniD: the same levelXdata schema) read from the raw per-recording CSV files.

The defaults follow the DNRI paper's inD setup: recordings in sorted order split 19 / 7 / 7 into train /
val / test, features [xCenter, yCenter, xVelocity, yVelocity] (metres, m/s), 25 Hz downsampled by 10 to
2.5 Hz, all road-user classes, min/max normalisation fitted on the present agents of the train split; its
forecast protocol (``conf/protocol/ind.yaml``) observes each agent for its own first 5 present steps
(``burn_in_mode=per_agent``, :mod:`dider.protocol`).

Recordings are found and split by :mod:`dider.data.levelx.recordings`, read and validated by
:mod:`dider.data.levelx.reading` and cut into packed windows of ``seq_len`` steps by
:mod:`dider.data.levelx.windows`; windows have different agent counts and are padded to the largest count
of each batch.

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
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, ClassVar

import matplotlib.image as plt_image
import numpy as np
import torch

from dider.data.batch import Normalizer
from dider.data.cache import cache_key, load_or_build
from dider.data.columns import csv_header, read_columns
from dider.data.common import SPLITS, BaseDataModule, PackedClipDataset, pad_collate, spread_indices
from dider.data.levelx.reading import WindowParams
from dider.data.levelx.recordings import RecordingFiles, discover_recordings, split_counts
from dider.data.levelx.source import LevelXSource
from dider.data.levelx.windows import concat_windows, preprocess_recording, select_windows
from dider.data.loader import Loader
from dider.data.pairs import PairRules, find_pairs
from dider.data.windowing import Windows
from dider.protocol import fill_absent
from dider.validation import Rule, check_settings

log = logging.getLogger(__name__)

CACHE_VERSION = 1  # part of the cache key: bump it when preprocessing changes what a cached file holds


class InDDataModule(BaseDataModule):
    """inD / rounD / uniD windows from the raw CSV files (see the module docstring).

    Batches: states [B, T, N, 4] (normalised; zeros for absent agents), mask [B, T, N] bool; N is the
    largest agent count in the batch. No ground-truth edges. After ``setup``: ``normalizer``,
    ``datasets`` (PackedClipDataset per split with extra attributes track_id, agent_class, class_names,
    window_start, window_recording, recordings), ``dt`` (seconds per step).
    """

    predicts = True
    units = "m"

    collate_fn = staticmethod(pad_collate)

    SETTINGS: ClassVar[dict[str, Rule | type]] = BaseDataModule.SETTINGS | {"source": LevelXSource,
                                                                             "windows": Windows}
    SOURCE = LevelXSource()  # inD's; data.source overrides it key by key
    WINDOWS = Windows(seq_len=50, downsample=10)  # DNRI's inD windows: 50 steps of 2.5 Hz
    UNUSED = {"max_speed": "levelX tracks come from a drone's view: no tracking jumps to drop"}
    LOADER = Loader(batch_size=8, eval_batch_size=8)  # DNRI's inD batch
    PAIRS = PairRules()  # the consistency check's rules; data.pairs overrides them key by key

    def __init__(
        self,
        source: Mapping[str, Any] | None = None,
        windows: Mapping[str, Any] | None = None,
        split: Sequence[float] = (19, 7, 7),
        pairs: dict[str, Any] | None = None,
        num_train: int | None = None,
        num_val: int | None = None,
        num_test: int | None = None,
        loader: Mapping[str, Any] | None = None,
        cache_dir: str | None = None,
    ) -> None:
        """source: the recordings (:class:`~dider.data.levelx.source.LevelXSource`): ``root``, the folder with each
        recording's ``{id}_tracks.csv``, ``_tracksMeta.csv`` and ``_recordingMeta.csv``; ``name``; ``recordings``;
        ``files`` and ``columns`` (their names); ``classes`` (the road users kept; null: all).
        windows: how recordings are cut (:class:`~dider.data.windowing.Windows`): ``downsample`` (10: 25 Hz ->
        2.5 Hz), ``seq_len`` steps (200 for the long-horizon table: ``data=ind200``), train windows every
        ``stride`` steps and val / test windows every ``eval_stride`` (null: seq_len, no overlap),
        ``min_agent_steps``, ``min_agents``, ``max_agents`` (the longest present kept; null: no cap).
        split: recordings for train / val / test in recording order (DNRI: 00-18 / 19-25 / 26-32), or fractions,
        e.g. [0.6, 0.2, 0.2].
        pairs: the consistency check on the test split (test/consistency/*: agent pairs whose edge type should stay
        the same all along): :class:`dider.data.pairs.PairRules` fields over ``PAIRS``; test batches carry
        ``pair_kind``."""
        super().__init__()
        check_settings(self, locals(), key="data")
        try:
            self.pair_rules = replace(self.PAIRS, **{k: tuple(v) if isinstance(v, list | tuple) else v
                                                     for k, v in dict(pairs or {}).items()})
        except TypeError as e:
            raise ValueError(f"data.pairs: {e} (fields: {list(PairRules.__dataclass_fields__)})") from None
        self.source = LevelXSource.of(source)
        self.windows = Windows.of(self.WINDOWS, windows, self.UNUSED)
        self.save_hyperparameters(logger=False)
        self.hparams["source"], self.hparams["windows"] = asdict(self.source), asdict(self.windows)  # as read
        self.init_shared()
        split_counts(split, available=10**9)  # form only; the recording count is known in prepare_data
        self.dt: float | None = None

    # -- files and cache

    def _root(self) -> Path:
        if self.source.root is None:
            raise ValueError(f"data.source.root is not set: point it at the folder with the {self.source.name} "
                             f"recordings ({self.source.files.tracks.format(id='XX')}, ...)")
        return Path(self.source.root).expanduser()

    def _discover(self) -> list[RecordingFiles]:
        f = self.source.files
        return discover_recordings(self._root(), f.tracks, f.tracks_meta, f.recording_meta, self.source.recordings)

    def split_recordings(self) -> dict[str, list[RecordingFiles]]:
        """Recordings of each split, in recording order: the first counts[0] train, then val, then test."""
        recs = self._discover()
        counts = split_counts(self.hparams.split, len(recs))
        if sum(counts) < len(recs):
            log.info("%s: using %d of %d recordings (data.split=%s)", self.source.name, sum(counts), len(recs),
                     list(self.hparams.split))
        bounds = np.cumsum([0, *counts])
        return {s: recs[bounds[i]:bounds[i + 1]] for i, s in enumerate(SPLITS)}

    def window_params(self, split: str) -> WindowParams:
        """What changes the windows of ``split``'s recordings (their cache key: the field names are the cache's)."""
        c, w = self.source.columns, self.windows
        stride = w.stride if split == "train" else w.eval_stride
        return WindowParams(
            track_id_column=c.track_id, frame_column=c.frame, class_column=c.agent_class,
            frame_rate_column=c.frame_rate, features=tuple(c.features),
            classes=None if self.source.classes is None else tuple(sorted(self.source.classes)),
            downsample=w.downsample, seq_len=w.seq_len, stride=stride or w.seq_len,
            min_agent_steps=w.min_agent_steps, min_agents=w.min_agents, max_agents=w.max_agents,
        )

    def cache_path(self, files: RecordingFiles, params: WindowParams) -> Path:
        key = cache_key({"version": CACHE_VERSION, "recording": files.id, "files": files.signature(),
                         "params": asdict(params)})
        return self.cache_dir / "levelx" / f"{self.source.name}_{files.id}_{key}.pt"

    def _load_or_build(self, files: RecordingFiles, params: WindowParams) -> dict[str, Any]:
        path = self.cache_path(files, params)

        def build() -> dict[str, Any]:
            t0 = time.perf_counter()
            blob = preprocess_recording(files, params)
            log.info("%s recording %s: %d windows from %d tracks in %.1f s -> %s", self.source.name, files.id,
                     len(blob["window_start"]), blob["num_tracks"], time.perf_counter() - t0, path)
            return blob

        return load_or_build(path, build)

    def prepare_data(self) -> None:
        """Read, validate and cache every recording once (rank 0 only under DDP)."""
        if self.normalizer is not None:  # prediction (use_normalizer): setup("predict") reads what it needs
            return
        for split, recs in self.split_recordings().items():
            params = self.window_params(split)
            for files in recs:
                if not self.cache_path(files, params).exists():
                    self._load_or_build(files, params)

    def recordings_of(self, split: str) -> list[RecordingFiles]:
        """The recordings of a split; ``predict``: every recording found (``data.recordings``), no split."""
        if split == "predict":
            return self._discover()
        return self.split_recordings()[split]

    def _windows(self, split: str, recs: list[RecordingFiles], rates: dict[str, float]) -> dict[str, Any]:
        """The packed windows of ``recs`` (cached per recording), capped for train / val / test."""
        h, w, classes = self.hparams, self.windows, self.source.classes
        blobs = [self._load_or_build(f, self.window_params(split)) for f in recs]
        rates.update({b["recording"]: b["frame_rate"] for b in blobs})
        data = concat_windows(blobs)
        if len(data["window_start"]) == 0:
            raise ValueError(
                f"{self.source.name} {split} split (recordings {[f.id for f in recs]}): no window of "
                f"data.windows.seq_len={w.seq_len} steps (x data.windows.downsample={w.downsample} = "
                f"{w.seq_len * w.downsample} frames) with >= data.windows.min_agents={w.min_agents} agents: "
                f"recordings too short or empty"
                + (f", or data.source.classes={list(classes)} left too few tracks" if classes else ""))
        cap = {"train": h.num_train, "val": h.num_val, "test": h.num_test}.get(split)
        if cap is not None and cap < len(data["window_start"]):
            data = select_windows(data, spread_indices(len(data["window_start"]), cap))
        return data

    def setup(self, stage: str | None = None) -> None:
        if self.datasets:
            return
        name, classes, downsample = self.source.name, self.source.classes, self.windows.downsample
        # predict: every recording, no split, the trained model's normalisation
        splits = ("predict",) if stage == "predict" else SPLITS
        rates: dict[str, float] = {}
        raw = {split: self._windows(split, self.recordings_of(split), rates) for split in splits}
        if classes is not None:  # a misspelt class silently selects nothing: say so
            seen = set().union(*(d["class_names"] for d in raw.values()))
            if unknown := sorted(set(classes) - seen):
                log.warning("data.source.classes: %s never occur in %s (classes present: %s)", unknown, name,
                            sorted(seen))
        # One downsample factor means one time step only if every recording has the same frame rate.
        if len(set(rates.values())) > 1:
            raise ValueError(f"{name}: recordings have different frame rates {rates} (recordingMeta "
                             f"{self.source.columns.frame_rate}); select recordings of one rate with "
                             f"data.source.recordings")
        self.dt = downsample / next(iter(rates.values()))
        self.frame_step = downsample
        if stage == "predict":
            self.predict_normalizer(f"data.source.root={self.source.root}")
        else:
            try:
                train = raw["train"]
                self.normalizer = self.train_normalizer(lambda: Normalizer.fit(train["states"], train["mask"]))
            except ValueError as e:  # e.g. only parked vehicles left: a zero velocity range
                raise ValueError(f"{name} train split (recordings {raw['train']['recordings']}): cannot "
                                 f"fit the normalisation: {e}") from None
        for split, data in raw.items():
            states = fill_absent(self.normalizer.normalize(data["states"]), data["mask"])
            pairs = None
            if split == "test":  # the consistency check reads raw speeds and paths
                vehicle = torch.tensor([c in self.pair_rules.vehicle_classes for c in data["class_names"]])
                pairs = find_pairs(data["states"], data["mask"], data["offsets"],
                                   vehicle[data["agent_class"]], self.pair_rules)
            # Where each window came from: its number in the split, its recording's id (window_recording
            # indexes this split's recordings), the recording's frame of its first step, the track ids.
            sources = {"clip": torch.arange(len(data["window_start"])),
                       "scene": self._recording_codes(data["recordings"])[data["window_recording"]],
                       "frame": data["window_start"] * downsample}
            ds = PackedClipDataset(states, data["mask"], data["offsets"], pairs, sources, data["track_id"])
            for key in ("track_id", "agent_class", "class_names", "window_start", "window_recording",
                        "recordings"):
                setattr(ds, key, data[key])
            self.datasets[split] = ds
        log.info("%s windows: %s", name, {s: len(d) for s, d in self.datasets.items()})

    def _recording_codes(self, recordings: list[str]) -> torch.Tensor:
        """Recording ids as source scene ids: the number itself for numeric ids ("07" -> 7), else a code
        into ``source_names["scene"]``."""
        if all(str(r).isdigit() for r in recordings):
            return torch.tensor([int(r) for r in recordings], dtype=torch.long)
        names = self.source_names.setdefault("scene", [])
        for r in recordings:
            if str(r) not in names:
                names.append(str(r))
        return torch.tensor([names.index(str(r)) for r in recordings], dtype=torch.long)

    def background(self, split: str, index: int) -> tuple[np.ndarray, tuple[float, float, float, float]] | None:
        """The background image of clip ``index`` of ``split`` and its extent (left, right, bottom, top) in
        the tracks' metres, for ``imshow``; None without the image or the recording's ``orthoPxToMeter``.

        A pixel is orthoPxToMeter * background_scale metres (the released images are downscaled) and the
        image's y axis points down while the tracks' points up."""
        ds = self.datasets[split]
        files = self.recordings_of(split)[int(ds.window_recording[index])]
        image = files.tracks.parent / self.source.files.background.format(id=files.id)
        if not image.is_file() or "orthoPxToMeter" not in csv_header(files.recording_meta):
            return None
        scale = self.source.background_scale
        meters = float(read_columns(files.recording_meta, ["orthoPxToMeter"]).iloc[0, 0]) * scale
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


LevelXDataModule = InDDataModule  # the same reader serves rounD and uniD
