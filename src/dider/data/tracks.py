"""The data module of every data set of long tracks: a table of rows (``data=table``, ``eth_ucy``, ``soccer``, a
user's reader) and the levelX drone recordings (``data=ind``, ``ind200``, ``round``, ``unid``).

``data.source`` says what is read; its ``reader`` picks the source (:data:`dider.data.track_sources.SOURCES`), whose
settings fill the rest of the node. The source reads its scenes (a table's scenes, a levelX data set's recordings)
and cuts each into windows by ``data.windows``, anchored at the scene's frames (:class:`Tracks`). The module splits
them, caps each split (``num_*``), fits the normaliser on the training windows and serves the batches: states [B, T,
N, 4] normalised (zeros where absent), mask [B, T, N] bool, the windows' source ids (``clip``, ``scene``, ``frame``,
``agent``) and, with ``data.pairs``, the test windows' agent pairs of the consistency check; N is the largest agent
count of the batch.

The split (``data.split``) follows the source. A table's scenes are cut first and split by a permutation seeded by
``data.seed``: by scene with >= 3 scenes that have windows (no window of a test scene is trained on), else by window;
``clip`` numbers the windows of the whole table. Recordings are split in recording order before the cut (counts, e.g.
DNRI's [19, 7, 7], or fractions); val and test windows start every ``data.windows.eval_stride`` steps; ``clip``
numbers the windows of each split.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import asdict, fields, replace
from typing import Any, ClassVar, Protocol

import numpy as np
import torch

from dider.data.batch import Normalizer
from dider.data.clip_splits import fractions_problem, split_counts, split_indices
from dider.data.common import SPLITS, BaseDataModule, PackedClipDataset, pad_collate, spread_indices
from dider.data.packed import select_windows
from dider.data.pairs import PairRules, find_pairs
from dider.data.track_sources import track_source
from dider.data.windowing import Windows
from dider.protocol import fill_absent
from dider.validation import ConfigError, Rule, check_settings

log = logging.getLogger(__name__)


class Tracks(Protocol):
    """A source's scenes once opened (``source.open(windows, cache_dir)``), as :class:`TracksDataModule` reads them.

    ``cut`` returns, per group, the packed windows of its scenes in scene order (raw units): states [P, T, 4] float32
    (zeros where absent), mask [P, T] bool, offsets [W+1] long (window w owns rows offsets[w]:offsets[w+1], agents
    by id), agent [P] long (ids, or codes into ``names["agent"]``), agent_class [P] long or None (codes into
    class_names), class_names, start [W] long (the window's first step in its scene), scene [W] long (index into
    ``scenes``), frame [W] long (the source's frame of the window's step 0). Optional: ``prepare(groups)`` (cache
    the groups' cuts; rank 0 under DDP) and ``background(scene)`` (an image to draw the scene's windows on)."""

    scenes: list[str]  # the scenes' names, in reading order
    scene_ids: torch.Tensor  # [Z] long: each scene's source id (its number, or a code into names["scene"])
    names: dict[str, list[str]]  # the names of string ids: scene, agent
    has_scene: bool  # whether the input names its scenes (a table without a scene column is one scene)
    frame_rate: float  # frames per second of the source's frames (known once cut)

    def cut(self, groups: Mapping[str, tuple[Sequence[int], int]]) -> dict[str, dict[str, Any]]:
        """group -> (scene indices, stride) to the group's windows."""
        ...


class TracksDataModule(BaseDataModule):
    """Windows of a data set of long tracks (module docstring). After ``setup``: ``normalizer``, ``datasets`` (a
    PackedClipDataset per split, with ``window_start``, ``window_scene`` (index into ``scenes``), ``scenes`` and,
    where the source has classes, ``agent_class`` and ``class_names``), ``source_names``, ``dt`` (seconds per step)
    and ``frame_step`` (source frames per step)."""

    predicts = True
    collate_fn = staticmethod(pad_collate)

    SETTINGS: ClassVar[dict[str, Rule | type]] = BaseDataModule.SETTINGS | {"windows": Windows}
    WINDOWS = Windows()  # what the config schema shows under windows; a null node takes the source's WINDOWS

    def __init__(
        self,
        source: Mapping[str, Any] | None = None,
        windows: Mapping[str, Any] | None = None,
        split: Sequence[float] | None = None,
        seed: int = 1,
        pairs: Mapping[str, Any] | None = None,
        num_train: int | None = None,
        num_val: int | None = None,
        num_test: int | None = None,
        loader: Mapping[str, Any] | None = None,
        cache_dir: str | None = None,
    ) -> None:
        """source: what is read (:mod:`dider.data.track_sources`): ``reader`` (``table``: a .csv / .parquet file's
        columns; a format's reader of :mod:`dider.data.readers`, e.g. ``eth_ucy``; ``kloppy``: a soccer provider's
        files; ``levelx``: inD / rounD / uniD recordings) and that reader's settings.
        windows: how scenes are cut (:class:`~dider.data.windowing.Windows`) over the source's defaults.
        split: train / val / test: fractions of a table's scenes (or windows), or recordings in order (counts or
        fractions); null: the source's default. seed: the seed of a table's split.
        pairs: the consistency check on the test split (agent pairs whose edge type should stay the same all along:
        :class:`dider.data.pairs.PairRules` fields over its defaults; test batches carry ``pair_kind``); needs agent
        classes; null: no check."""
        super().__init__()
        self.source = track_source(source)
        cls = type(self.source)
        split = list(cls.SPLIT if split is None else split)
        check_settings(self, locals(), {"split": (split, self._split_problem)}, key="data")
        self.windows = Windows.of(cls.WINDOWS, windows, cls.UNUSED)
        if cls.IN_ORDER and seed != 1:
            raise ConfigError(f"data.seed={seed}: data.source.reader={self.source.reader} splits its recordings in "
                              f"order; the seed is a table's")
        self.pair_rules = None if pairs is None else _pair_rules(pairs)
        self.save_hyperparameters(logger=False)
        h = self.hparams
        h["source"], h["windows"], h["split"] = asdict(self.source), asdict(self.windows), split  # as read
        self.init_shared()
        self.units = cls.UNITS
        self.frame_step = self.windows.downsample
        self.dt: float | None = None
        self._tracks: Tracks | None = None

    def _split_problem(self, split: object) -> str | None:
        if type(self.source).IN_ORDER:
            try:
                split_counts(split, available=10**9)  # form only; the recording count is known once opened
            except (ValueError, TypeError) as e:
                return str(e).split(": ", 1)[-1]
            return None
        return fractions_problem(split)

    def tracks(self) -> Tracks:
        """The source opened (once): its scenes, read or found."""
        if self._tracks is None:
            self._tracks = self.source.open(self.windows, self.cache_dir)
        return self._tracks

    def _groups(self, stage: str | None) -> dict[str, tuple[list[int], int]]:
        """What is cut, each group with its stride: every scene for prediction (as val and test are cut) or a
        table's split; each split's recordings for a split in order."""
        w, scenes = self.windows, range(len(self.tracks().scenes))
        eval_stride = (w.eval_stride or w.seq_len) if type(self.source).IN_ORDER else (w.stride or w.seq_len)
        if stage == "predict":
            return {"predict": (list(scenes), eval_stride)}
        if not type(self.source).IN_ORDER:
            return {"all": (list(scenes), w.stride or w.seq_len)}
        counts = split_counts(self.hparams.split, len(scenes))
        if sum(counts) < len(scenes):
            log.info("%s: using %d of %d recordings (data.split=%s)", self.source.where(), sum(counts), len(scenes),
                     list(self.hparams.split))
        bounds = np.cumsum([0, *counts]).tolist()
        return {s: (list(range(bounds[i], bounds[i + 1])), w.stride or w.seq_len if s == "train" else eval_stride)
                for i, s in enumerate(SPLITS)}

    def prepare_data(self) -> None:
        """Cache what the source caches (rank 0 only under DDP); prediction reads what it needs in setup."""
        if self.normalizer is None and hasattr(tracks := self.tracks(), "prepare"):
            tracks.prepare(self._groups("fit"))

    def setup(self, stage: str | None = None) -> None:
        if ({"predict"} if stage == "predict" else set(SPLITS)) <= set(self.datasets):
            return
        # prediction: every window, no split, the trained model's normalisation (checked before anything is read)
        normalizer = self.predict_normalizer(self.source.where()) if stage == "predict" else None
        tracks = self.tracks()
        cuts = tracks.cut(self._groups(stage))
        for cut in cuts.values():  # a window's number among those cut with it: the table's, or its split's
            cut["clip"] = torch.arange(len(cut["frame"]))
            if self.pair_rules is not None and cut["agent_class"] is None:
                raise ValueError(f"data.pairs: the consistency check needs the agents' classes, and "
                                 f"{self.source.where()} has none (a table's: data.source.columns.agent_class)")
        if getattr(self.source, "frame_rate", 0) is None:  # a source that reads its rate: the checkpoint carries it
            self.source = replace(self.source, frame_rate=tracks.frame_rate)
            self.hparams["source"] = asdict(self.source)
        self.dt = self.windows.downsample / tracks.frame_rate
        self.source_names = {k: v for k, v in tracks.names.items() if k in ("scene", "agent")}
        if normalizer is not None:
            self.datasets["predict"] = self._dataset(cuts["predict"], normalizer, "predict")
            return
        parts, by = self._split(cuts)
        try:
            self.normalizer = self.train_normalizer(
                lambda: Normalizer.fit(parts["train"]["states"], parts["train"]["mask"]))
        except ValueError as e:  # e.g. agents that never move: a zero velocity range
            raise ValueError(f"{self.source.where()}: cannot fit the normalisation on the train split: {e}") from None
        for split in SPLITS:
            self.datasets[split] = self._dataset(parts[split], self.normalizer, split)
        log.info("%s: %d scenes, split by %s: %s windows", self.source.where(), len(tracks.scenes), by,
                 {s: len(d) for s, d in self.datasets.items()})

    def _split(self, cuts: dict[str, dict[str, Any]]) -> tuple[dict[str, dict[str, Any]], str]:
        """The windows of each split, capped: a table's split by scene when >= 3 scenes have windows, else by
        window; recordings split in order come cut by split."""
        h = self.hparams
        if "all" in cuts:
            cut = cuts["all"]
            scenes = torch.unique(cut["scene"])
            by = "scene" if len(scenes) >= 3 else "window"
            try:
                idx = split_indices(len(scenes) if by == "scene" else len(cut["frame"]), h.split, h.seed)
            except ValueError as e:
                raise ValueError(f"{self.source.where()}: {len(cut['frame'])} windows: {e}") from None
            if by == "scene":
                idx = {s: torch.isin(cut["scene"], scenes[p]).nonzero().squeeze(1) for s, p in idx.items()}
            if by == "window" and (self.windows.stride or self.windows.seq_len) < self.windows.seq_len:
                log.warning("data.windows.stride=%d < data.windows.seq_len=%d with a split by window: val / test "
                            "windows share steps with training windows", self.windows.stride, self.windows.seq_len)
        else:
            cut, by = None, "recording, in order"
        caps = {"train": h.num_train, "val": h.num_val, "test": h.num_test}
        parts = {}
        for split in SPLITS:
            whole = cuts[split] if cut is None else select_windows(cut, idx[split])
            parts[split] = select_windows(whole, spread_indices(len(whole["frame"]), caps[split]))
        return parts, by

    def _dataset(self, cut: dict[str, Any], normalizer: Normalizer, split: str) -> PackedClipDataset:
        """A split's windows, normalised, with their source ids (and the test split's pairs)."""
        tracks = self.tracks()
        states = fill_absent(normalizer.normalize(cut["states"]), cut["mask"])
        pairs = None
        if split == "test" and self.pair_rules is not None:  # the consistency check reads raw speeds and paths
            vehicle = torch.tensor([c in self.pair_rules.vehicle_classes for c in cut["class_names"]])
            pairs = find_pairs(cut["states"], cut["mask"], cut["offsets"], vehicle[cut["agent_class"]],
                               self.pair_rules)
        sources = {"clip": cut["clip"], "scene": tracks.scene_ids[cut["scene"]], "frame": cut["frame"]}
        if not tracks.has_scene:
            sources.pop("scene")
        ds = PackedClipDataset(states, cut["mask"], cut["offsets"], pairs, sources, cut["agent"])
        ds.window_start, ds.window_scene, ds.scenes = cut["start"], cut["scene"], tracks.scenes
        if cut["agent_class"] is not None:
            ds.agent_class, ds.class_names = cut["agent_class"], cut["class_names"]
        return ds

    def background(self, split: str, index: int) -> tuple[np.ndarray, tuple[float, float, float, float]] | None:
        """The background image of window ``index`` of ``split`` and its extent (left, right, bottom, top) in the
        tracks' units, where the source has one (levelX recordings)."""
        tracks = self.tracks()
        if not hasattr(tracks, "background"):
            return None
        return tracks.background(int(self.datasets[split].window_scene[index]))


def _pair_rules(given: Mapping[str, Any]) -> PairRules:
    """``data.pairs`` over :class:`PairRules`' defaults; an unknown key names the fields."""
    try:
        return PairRules(**{k: tuple(v) if isinstance(v, list | tuple) else v for k, v in dict(given).items()})
    except TypeError as e:
        raise ValueError(f"data.pairs: {e} (fields: {[f.name for f in fields(PairRules)]})") from None
