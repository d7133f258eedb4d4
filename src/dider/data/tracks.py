"""The data module of every data set of long tracks: a table of rows (``data=table``, ``eth_ucy``, ``soccer``, a
user's own format) and the levelX drone recordings (``data=ind``, ``ind200``, ``round``, ``unid``).

``data.source`` says what is read: its ``_target_`` names the track source's class (:class:`TrackSource`: dider's in
:mod:`dider.data.track_sources`, :mod:`dider.data.readers` and :mod:`dider.data.levelx`, or one of the user's own),
whose settings fill the rest of the node. The source reads its scenes (a table's scenes, a levelX data set's
recordings) and cuts each into windows by ``data.windows``, anchored at the scene's frames (:class:`Tracks`, which
gives :class:`~dider.data.packed.PackedWindows`). The module splits
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
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np
import torch

from dider.data.batch import Normalizer
from dider.data.clip_splits import (
    SPLIT_SEED,
    counts_problem,
    fractions_problem,
    split_counts,
    split_indices,
    split_problem,
)
from dider.data.common import SPLITS, BaseDataModule, PackedClipDataset, pad_collate, spread_indices
from dider.data.packed import PackedWindows
from dider.data.pairs import PairRules, find_pairs
from dider.data.sources import data_source, recorded_source
from dider.data.track_sources import TableFile
from dider.data.windowing import Windows
from dider.protocol import fill_absent
from dider.targets import class_path
from dider.validation import ClassNode, Rule, check_settings

log = logging.getLogger(__name__)


class Tracks(Protocol):
    """A source's scenes once opened (``source.open(windows, cache_dir)``), as :class:`TracksDataModule` reads them.

    ``cut`` returns, per group, the windows of its scenes in scene order (:class:`~dider.data.packed.PackedWindows`,
    raw units: positions less the ``origin`` it is given, subtracted before any float32 rounding; ``frame``: a
    table's steps count from the scene's first frame, its first step dropped where velocities are differenced; a
    recording's from frame 0). Optional: ``prepare(groups)`` (cache the groups' cuts; rank 0 under DDP) and
    ``background(scene)`` (an image to draw the scene's windows on)."""

    scenes: list[str]  # the scenes' names, in reading order
    scene_ids: torch.Tensor  # [Z] long: each scene's source id (its number, or a code into names["scene"])
    names: dict[str, list[str]]  # the names of string ids: scene, agent (agent_class)
    has_scene: bool  # whether the input names its scenes (a table without a scene column is one scene)
    has_classes: bool  # whether the agents have classes (agent_class in the cuts)
    frame_rate: float  # frames per second of the source's frames (known once cut)
    origin: tuple[float, float]  # (x0, y0) the windows of a training run are relative to: the source's centre

    def cut(self, groups: Mapping[str, tuple[Sequence[int], int]],
            origin: tuple[float, float]) -> dict[str, PackedWindows]:
        """group -> (scene indices, stride) to the group's windows, positions relative to ``origin``."""
        ...


class TrackSource(Protocol):
    """A track source as :class:`TracksDataModule` reads it: a class that a data config's ``data.source._target_``
    names (dider's or one in a package of the user's own), its settings the node's other keys, best a frozen
    dataclass (what a checkpoint records of it: the fields). A table format's class derives from
    :class:`~dider.data.track_sources.TrackFile`, which has all of these but ``read``. Optional: ``frame_rate`` (a
    setting; None: the tracks say theirs once cut, and the checkpoint records it)."""

    WINDOWS: ClassVar[Windows]  # the windows' defaults (data.windows overrides them key by key)
    UNUSED: ClassVar[dict[str, str]]  # the window settings it does not read, and why
    SPLIT: ClassVar[tuple[float, ...]]  # data.split's default
    IN_ORDER: ClassVar[bool]  # its scenes are recordings split in order before the cut (else a table's)
    UNITS: ClassVar[str | None]  # the positions' unit, for scale bars (None: unknown)

    def open(self, windows: Windows, cache_dir: Path) -> Tracks:
        """Its scenes, to be cut by ``windows`` (cached under ``cache_dir`` where the source caches)."""
        ...

    def where(self) -> str:
        """What error messages name the input by (``data.source.path=...``)."""
        ...


class TracksDataModule(BaseDataModule):
    """Windows of a data set of long tracks (module docstring). After ``setup``: ``normalizer``, ``datasets`` (a
    PackedClipDataset per split, with ``window_start`` and ``window_scene`` (the window's first step and its scene,
    an index into ``scenes``), ``scenes`` and, where the source has classes, ``agent_class`` and ``class_names``),
    ``source_names``, ``dt`` (seconds per step; a table's from the start, a levelX data set's once its recordings
    are read) and ``frame_step`` (source frames per step)."""

    predicts = True
    collate_fn = staticmethod(pad_collate)

    SOURCE_KIND: ClassVar[str] = "track source"  # what data.source builds (dider.targets)
    SETTINGS: ClassVar[dict[str, Rule | type | ClassNode]] = BaseDataModule.SETTINGS | {
        "source": ClassNode(SOURCE_KIND), "windows": Windows,
        "split": split_problem, "pairs": PairRules,
        "seed": SPLIT_SEED}

    def __init__(
        self,
        source: TrackSource | Mapping[str, Any] | None = None,
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
        """source: what is read: a track source, or its node (``_target_``, the class, and its settings), e.g.
        :class:`~dider.data.track_sources.TableFile` (a .csv / .parquet file's columns; the default),
        :class:`~dider.data.readers.eth_ucy.EthUcyFiles` (a format's files),
        :class:`~dider.data.track_sources.KloppySource` (a soccer provider's files) or
        :class:`~dider.data.levelx.source.LevelXSource` (inD / rounD / uniD recordings).
        windows: how scenes are cut (:class:`~dider.data.windowing.Windows`) over the source's defaults (``WINDOWS``).
        split: train / val / test: fractions of a table's scenes (or windows), or recordings in order (counts or
        fractions); null: the source's (``SPLIT``). seed: the seed of a table's split.
        pairs: the consistency check on the test split (agent pairs whose edge type should stay the same all along:
        :class:`dider.data.pairs.PairRules` fields over its defaults; test batches carry ``pair_kind``); needs agent
        classes; null: no check."""
        super().__init__()
        self.source: TrackSource = data_source(source, self.SOURCE_KIND, default=TableFile)
        cls = type(self.source)
        split = cls.SPLIT if split is None else split
        in_order = "splits its recordings in order; the seed is a table's"
        check_settings(self, {**locals(), "split": None}, {  # the split by its source's rule alone
            "split": (split, counts_problem if cls.IN_ORDER else fractions_problem),
            "seed": (seed, lambda v: f"data.source._target_={class_path(cls)} {in_order}" if cls.IN_ORDER and v != 1
                     else None)}, key="data")
        self.windows = Windows.of(cls.WINDOWS, windows, cls.UNUSED)
        self.pair_rules = None if pairs is None else _pair_rules(pairs)
        self.save_hyperparameters(logger=False)
        h = self.hparams
        h["source"], h["windows"], h["split"] = recorded_source(self.source), asdict(self.windows), list(split)
        self.init_shared()
        self.units = cls.UNITS
        self.frame_step = self.windows.downsample
        rate = getattr(self.source, "frame_rate", None)  # a table's; levelX recordings say theirs as they are read
        self.dt: float | None = None if rate is None else self.windows.downsample / rate
        self._tracks: Tracks | None = None

    def tracks(self) -> Tracks:
        """The source opened (once): its scenes, read or found."""
        if self._tracks is None:
            self._tracks = self.source.open(self.windows, self.cache_dir)
        return self._tracks

    def _groups(self, stage: str | None) -> dict[str, tuple[list[int], int]]:
        """What is cut, each group with its stride: a table's every scene (split after the cut); each split's
        recordings in order (val and test every ``eval_stride``); for prediction every scene, as val and test are
        cut."""
        w, scenes = self.windows, list(range(len(self.tracks().scenes)))
        stride = w.stride or w.seq_len
        in_order = type(self.source).IN_ORDER
        eval_stride = (w.eval_stride or w.seq_len) if in_order else stride  # a table's val and test: its one cut
        if stage == "predict":
            return {"predict": (scenes, eval_stride)}
        if not in_order:
            return {"all": (scenes, stride)}
        counts = split_counts(self.hparams.split, len(scenes))
        if sum(counts) < len(scenes):
            log.info("%s: using %d of %d recordings (data.split=%s)", self.source.where(), sum(counts), len(scenes),
                     list(self.hparams.split))
        bounds = np.cumsum([0, *counts]).tolist()
        return {s: (scenes[bounds[i]:bounds[i + 1]], stride if s == "train" else eval_stride)
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
        if normalizer is None and self.pair_rules is not None and not tracks.has_classes:
            raise ValueError(f"data.pairs: the consistency check needs the agents' classes, and "
                             f"{self.source.where()} has none (a table's: data.source.columns.agent_class)")
        # A trained model's windows are relative to its training origin; a new run's to the source's centre.
        trained = normalizer if normalizer is not None else self.normalizer
        origin = trained.origin if trained is not None else tracks.origin
        cuts = tracks.cut(self._groups(stage), origin)
        if getattr(self.source, "frame_rate", 0) is None:  # a source that reads its rate: the checkpoint carries it
            self.source = replace(self.source, frame_rate=tracks.frame_rate)
            self.hparams["source"] = recorded_source(self.source)
        self.dt = self.windows.downsample / tracks.frame_rate
        self.source_names = {k: v for k, v in tracks.names.items() if k in ("scene", "agent")}
        if normalizer is not None:
            self.datasets["predict"] = self._dataset(cuts["predict"].numbered(), normalizer, "predict")
            log.info("%s: %d windows to predict", self.source.where(), len(self.datasets["predict"]))
            return
        parts, by = self._split(cuts)
        train = parts["train"]
        try:
            self.normalizer = self.train_normalizer(lambda: Normalizer.fit(train.states, train.mask, origin))
        except ValueError as e:  # e.g. agents that never move: a zero velocity range
            scenes = [tracks.scenes[i] for i in torch.unique(train.scene).tolist()]
            raise ValueError(f"{self.source.where()}: cannot fit the normalisation on the train split (scenes "
                             f"{scenes}): {e}") from None
        for split in SPLITS:
            self.datasets[split] = self._dataset(parts[split], self.normalizer, split)
        used = len(torch.unique(torch.cat([p.scene for p in parts.values()])))
        log.info("%s: %d windows of %d scenes, split by %s: %s", self.source.where(),
                 sum(len(d) for d in self.datasets.values()), used, by, {s: len(d) for s, d in self.datasets.items()})

    def _split(self, cuts: dict[str, PackedWindows]) -> tuple[dict[str, PackedWindows], str]:
        """The windows of each split, capped (``num_*``) and numbered (``clip``): a table's windows numbered over the
        table, then split by scene when >= 3 scenes have windows, else by window; recordings come cut by split, each
        split's windows numbered after its cap."""
        h = self.hparams
        caps = {"train": h.num_train, "val": h.num_val, "test": h.num_test}

        def capped(cut: PackedWindows, split: str) -> PackedWindows:
            return cut.select(spread_indices(len(cut), caps[split]))

        if type(self.source).IN_ORDER:
            return {split: capped(cuts[split], split).numbered() for split in SPLITS}, "recording, in order"
        cut = cuts["all"].numbered()
        scenes = torch.unique(cut.scene)
        by = "scene" if len(scenes) >= 3 else "window"
        try:
            idx = split_indices(len(scenes) if by == "scene" else len(cut), h.split, h.seed)
        except ValueError as e:
            raise ValueError(f"{self.source.where()}: {len(cut)} windows: {e}") from None
        if by == "scene":
            idx = {s: torch.isin(cut.scene, scenes[p]).nonzero().squeeze(1) for s, p in idx.items()}
        elif (self.windows.stride or self.windows.seq_len) < self.windows.seq_len:
            log.warning("data.windows.stride=%d < data.windows.seq_len=%d with a split by window: val / test windows "
                        "share steps with training windows", self.windows.stride, self.windows.seq_len)
        return {split: capped(cut.select(idx[split]), split) for split in SPLITS}, by

    def _dataset(self, cut: PackedWindows, normalizer: Normalizer, split: str) -> PackedClipDataset:
        """A split's windows, normalised, with their source ids (and the test split's pairs)."""
        tracks = self.tracks()
        states = fill_absent(normalizer.normalize(cut.states), cut.mask)
        pairs = None
        if split == "test" and self.pair_rules is not None:  # the consistency check reads raw speeds and paths
            vehicle = torch.tensor([c in self.pair_rules.vehicle_classes for c in cut.class_names])
            pairs = find_pairs(cut.states, cut.mask, cut.offsets, vehicle[cut.agent_class], self.pair_rules)
        sources = {"clip": cut.clip, "scene": tracks.scene_ids[cut.scene], "frame": cut.frame}
        if not tracks.has_scene:
            sources.pop("scene")
        ds = PackedClipDataset(states, cut.mask, cut.offsets, pairs, sources, cut.agent)
        ds.window_start, ds.window_scene, ds.scenes = cut.start, cut.scene, tracks.scenes
        if cut.agent_class is not None:
            ds.agent_class, ds.class_names = cut.agent_class, cut.class_names
        return ds

    def background(self, split: str, index: int) -> tuple[np.ndarray, tuple[float, float, float, float]] | None:
        """The background image of window ``index`` of ``split`` and its extent (left, right, bottom, top) in the
        tracks' units, where the source has one (levelX recordings)."""
        tracks = self.tracks()
        if not hasattr(tracks, "background"):
            return None
        return tracks.background(int(self.datasets[split].window_scene[index]))


def _pair_rules(given: Mapping[str, Any]) -> PairRules:
    """``data.pairs`` (its keys checked by ``SETTINGS``) over :class:`PairRules`' defaults; lists as tuples."""
    return PairRules(**{k: tuple(v) if isinstance(v, list | tuple) else v for k, v in dict(given).items()})
