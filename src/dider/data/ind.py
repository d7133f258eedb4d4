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
from dider.data.common import SPLITS, ClipDataModule, PackedClipDataset, pad_collate, spread_indices
from dider.data.levelx.reading import DEFAULT_FEATURES, WindowParams
from dider.data.levelx.recordings import RecordingFiles, discover_recordings, pattern_regex, split_counts
from dider.data.levelx.windows import concat_windows, preprocess_recording, select_windows
from dider.data.loader import Loader
from dider.data.pairs import PairRules, find_pairs
from dider.protocol import fill_absent
from dider.validation import Rule, check_settings, integer, optional

log = logging.getLogger(__name__)

CACHE_VERSION = 1  # part of the cache key: bump it when preprocessing changes what a cached file holds


class InDDataModule(ClipDataModule):
    """inD / rounD / uniD windows from the raw CSV files (see the module docstring).

    Batches: states [B, T, N, 4] (normalised; zeros for absent agents), mask [B, T, N] bool; N is the
    largest agent count in the batch. No ground-truth edges. After ``setup``: ``normalizer``,
    ``datasets`` (PackedClipDataset per split with extra attributes track_id, agent_class, class_names,
    window_start, window_recording, recordings), ``dt`` (seconds per step).
    """

    predicts = True
    units = "m"

    collate_fn = staticmethod(pad_collate)

    SETTINGS: ClassVar[dict[str, Rule | type]] = ClipDataModule.SETTINGS | {
        "downsample": integer(1), "seq_len": integer(2), "stride": optional(integer(1)),
        "eval_stride": optional(integer(1)), "min_agent_steps": integer(1), "min_agents": integer(1),
        "max_agents": optional(integer(1)),
    }
    LOADER = Loader(batch_size=8, eval_batch_size=8)  # DNRI's inD batch
    PAIRS = PairRules()  # the consistency check's rules; data.pairs overrides them key by key

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
        min_agent_steps: int = 1,
        min_agents: int = 2,
        max_agents: int | None = None,
        num_train: int | None = None,
        num_val: int | None = None,
        num_test: int | None = None,
        loader: Mapping[str, Any] | None = None,
        cache_dir: str | None = None,
        pairs: dict[str, Any] | None = None,
        background_pattern: str = "{id}_background.png",
        background_scale: float = 12.0,
    ) -> None:
        """root: the folder with each recording's ``{id}_tracks.csv``, ``_tracksMeta.csv`` and ``_recordingMeta.csv``.
        name: the data set's name: the cache files' prefix and the log messages.
        recordings: the recording ids used, e.g. [0, 1, 7]; null: every recording found, in order.
        split: recordings for train / val / test in recording order (DNRI: 00-18 / 19-25 / 26-32), or fractions,
        e.g. [0.6, 0.2, 0.2].
        class_column: a column of tracksMeta.
        frame_rate_column: a column of recordingMeta.
        features: x, y (m), x and y velocity (m/s); the files' other columns are ignored.
        classes: the road-user classes kept, e.g. [car, truck_bus]; null: all (DNRI).
        downsample: keep every k-th frame (10: 25 Hz -> 2.5 Hz).
        seq_len: the window length in downsampled steps (200 for the long-horizon table: ``data=ind200``).
        stride: train windows start every ``stride`` steps; null: seq_len (no overlap).
        eval_stride: the same for val / test windows; null: seq_len.
        min_agent_steps: keep the agents present for at least this many steps of a window.
        min_agents: drop windows with fewer agents (relations need two).
        max_agents: cap on the agents per window (the longest present kept); null: no cap.
        pairs: the consistency check on the test split (test/consistency/*: agent pairs whose edge type should stay
        the same all along): :class:`dider.data.pairs.PairRules` fields over ``PAIRS``; test batches carry
        ``pair_kind``.
        background_pattern: the image drawn under the trajectory figures, where present.
        background_scale: metres per background pixel = orthoPxToMeter x this (inD's images are downscaled 12x)."""
        super().__init__()
        check_settings(self, locals(), key="data")
        try:
            self.pair_rules = replace(self.PAIRS, **{k: tuple(v) if isinstance(v, list | tuple) else v
                                                     for k, v in dict(pairs or {}).items()})
        except TypeError as e:
            raise ValueError(f"data.pairs: {e} (fields: {list(PairRules.__dataclass_fields__)})") from None
        if max_agents is not None and max_agents < min_agents:
            raise ValueError(f"data.max_agents={max_agents}: must be >= data.min_agents={min_agents}")
        if min_agent_steps > seq_len:
            raise ValueError(f"data.min_agent_steps={min_agent_steps}: must be <= data.seq_len={seq_len}")
        if len(features) != 4:
            raise ValueError(f"data.features={list(features)}: need 4 columns (x, y, x velocity, y velocity)")
        self.save_hyperparameters(logger=False)
        self.init_shared()
        for key, pattern in [("tracks_pattern", tracks_pattern), ("tracks_meta_pattern", tracks_meta_pattern),
                             ("recording_meta_pattern", recording_meta_pattern)]:
            try:
                pattern_regex(pattern)
            except ValueError as e:
                raise ValueError(f"data.{key}: {e}") from None
        split_counts(split, available=10**9)  # form only; the recording count is known in prepare_data
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

        def build() -> dict[str, Any]:
            t0 = time.perf_counter()
            blob = preprocess_recording(files, params)
            log.info("%s recording %s: %d windows from %d tracks in %.1f s -> %s", self.hparams.name, files.id,
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
            h = self.hparams
            return discover_recordings(self._root(), h.tracks_pattern, h.tracks_meta_pattern,
                                       h.recording_meta_pattern, h.recordings)
        return self.split_recordings()[split]

    def _windows(self, split: str, recs: list[RecordingFiles], rates: dict[str, float]) -> dict[str, Any]:
        """The packed windows of ``recs`` (cached per recording), capped for train / val / test."""
        h = self.hparams
        blobs = [self._load_or_build(f, self.window_params(split)) for f in recs]
        rates.update({b["recording"]: b["frame_rate"] for b in blobs})
        data = concat_windows(blobs)
        if len(data["window_start"]) == 0:
            raise ValueError(
                f"{h.name} {split} split (recordings {[f.id for f in recs]}): no window of data.seq_len="
                f"{h.seq_len} steps (x data.downsample={h.downsample} = "
                f"{h.seq_len * h.downsample} frames) with >= data.min_agents={h.min_agents} agents: "
                f"recordings too short or empty"
                + (f", or data.classes={list(h.classes)} left too few tracks" if h.classes else ""))
        cap = {"train": h.num_train, "val": h.num_val, "test": h.num_test}.get(split)
        if cap is not None and cap < len(data["window_start"]):
            data = select_windows(data, spread_indices(len(data["window_start"]), cap))
        return data

    def setup(self, stage: str | None = None) -> None:
        if self.datasets:
            return
        h = self.hparams
        # predict: every recording, no split, the trained model's normalisation
        splits = ("predict",) if stage == "predict" else SPLITS
        rates: dict[str, float] = {}
        raw = {split: self._windows(split, self.recordings_of(split), rates) for split in splits}
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
        self.frame_step = h.downsample
        if stage == "predict":
            self.predict_normalizer(f"data.root={h.root}")
        else:
            try:
                train = raw["train"]
                self.normalizer = self.train_normalizer(lambda: Normalizer.fit(train["states"], train["mask"]))
            except ValueError as e:  # e.g. only parked vehicles left: a zero velocity range
                raise ValueError(f"{h.name} train split (recordings {raw['train']['recordings']}): cannot "
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
                       "frame": data["window_start"] * h.downsample}
            ds = PackedClipDataset(states, data["mask"], data["offsets"], pairs, sources, data["track_id"])
            for key in ("track_id", "agent_class", "class_names", "window_start", "window_recording",
                        "recordings"):
                setattr(ds, key, data[key])
            self.datasets[split] = ds
        log.info("%s windows: %s", h.name, {s: len(d) for s, d in self.datasets.items()})

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
        h, ds = self.hparams, self.datasets[split]
        files = self.recordings_of(split)[int(ds.window_recording[index])]
        image = files.tracks.parent / h.background_pattern.format(id=files.id)
        if not image.is_file() or "orthoPxToMeter" not in csv_header(files.recording_meta):
            return None
        meters = float(read_columns(files.recording_meta, ["orthoPxToMeter"]).iloc[0, 0]) * h.background_scale
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
