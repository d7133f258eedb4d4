"""The data module of every data set that comes as fixed-length clips: the simulators (``data=synth``, ``springs``,
``charged``) and the files that ship clips (``nri_files``, ``dnri_files``, ``basketball``, ``trajectories``).

``data.source`` says what is read or simulated: its ``_target_`` names the clip source's class
(:class:`~dider.data.clip_source.ClipSource`: dider's in :mod:`dider.data.simulators` and :mod:`dider.data.readers`,
or one of the user's own), whose settings fill the rest of the node. The module makes the source's parts into the
three splits (a file of clips split by ``split`` fractions, a validation split carved from the training files by
``val_fraction``; ``seed`` seeds both), crops the training clips (``train_len``), caps each split (``num_*``; a
simulator's sizes), fits the normaliser (``normalization``) on the training split and serves the batches: states
[B, T, N, 4] normalised, mask [B, T, N], edges [B, T-1, E] long where the source has them, and the clips' ids as
``source``.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

from dider.data.clip_source import Clips, ClipSource
from dider.data.clip_splits import (
    RANGES,
    SPLIT_SEED,
    capped,
    carve,
    clip_datasets,
    fit_ranges,
    fractions_problem,
    split_indices,
)
from dider.data.common import SPLITS, BaseDataModule
from dider.data.sources import data_source, recorded_source
from dider.targets import class_path
from dider.validation import ClassNode, ConfigError, Rule, check_settings, integer, one_of, optional, within_open

log = logging.getLogger(__name__)

# The settings that make the three splits, their defaults and the sources that read them: a source names those it
# reads in ``SPLIT_SETTINGS``; another one set away from its default is refused.
SPLIT_DEFAULTS = {"split": [0.8, 0.1, 0.1], "val_fraction": 0.1, "seed": 1}
WHO_READS = {"split": "a source of one file of clips (dider.data.readers.trajectories.NpzFile)",
             "val_fraction": "a source whose files may lack a validation split "
                             "(dider.data.readers.basketball.BasketballFiles)",
             "seed": "the sources that split or carve (NpzFile, BasketballFiles)"}


class ClipsDataModule(BaseDataModule):
    """Fixed-length clips from a clip source (module docstring). After ``setup``: ``normalizer``, ``datasets`` (a
    ClipDataset per split); ``setup("predict")`` serves every clip of a source that has a prediction set (``.npz``
    trajectories, DNRI's files), normalised with the trained model's normaliser."""

    SOURCE_KIND: ClassVar[str] = "clip source"  # what data.source builds (dider.targets)
    SETTINGS: ClassVar[dict[str, Rule | type | ClassNode]] = BaseDataModule.SETTINGS | {
        "source": ClassNode(SOURCE_KIND), "normalization": one_of(*RANGES), "split": fractions_problem,
        "val_fraction": within_open(0, 1), "seed": SPLIT_SEED,
        "train_len": optional(integer(2))}

    def __init__(
        self,
        source: ClipSource | Mapping[str, Any] | None = None,
        normalization: str = "separate",
        split: Sequence[float] = (0.8, 0.1, 0.1),
        val_fraction: float = 0.1,
        seed: int = 1,
        train_len: int | None = None,
        num_train: int | None = None,
        num_val: int | None = None,
        num_test: int | None = None,
        loader: Mapping[str, Any] | None = None,
        cache_dir: str | None = None,
    ) -> None:
        """source: what is read or simulated: a clip source, or its node (``_target_``, the class, and its
        settings).
        normalization: separate (positions and velocities each by their own range), same (one range) or none.
        split: train / val / test fractions of a source that gives one file of clips (a permutation seeded by
        ``seed``). val_fraction: the training clips carved off for validation where the files have no validation
        split (seeded by ``seed``). train_len: crop training clips to their first steps; null: whole clips.
        num_train, num_val, num_test: a simulator's split sizes (required); else a cap on each split's clips."""
        super().__init__()
        self.source: ClipSource = data_source(source, self.SOURCE_KIND)
        cls = type(self.source)
        sizes = {"num_train": num_train, "num_val": num_val, "num_test": num_test}
        self.generated = getattr(cls, "GENERATED", False)  # num_* are the sizes to simulate, not caps
        related = {k: (v, integer(1, " (the simulated split's size)")) for k, v in sizes.items()} \
            if self.generated else {}
        check_settings(self, locals(), related, key="data")
        reads = getattr(cls, "SPLIT_SETTINGS", ())
        splitting = {"split": list(split), "val_fraction": val_fraction, "seed": seed}
        if unread := [f"data.{k}={v!r}: data.source._target_={class_path(cls)} gives its splits as they are; read "
                      f"by {WHO_READS[k]}" for k, v in splitting.items() if k not in reads and v != SPLIT_DEFAULTS[k]]:
            raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(unread))
        self.save_hyperparameters(logger=False)
        self.hparams["source"] = recorded_source(self.source)  # as read, the node that builds it again
        self.init_shared()
        self.units = getattr(cls, "UNITS", None)
        self.predicts = hasattr(self.source, "predict_clips")

    def _sizes(self) -> dict[str, int | None]:
        return {split: self.hparams[f"num_{split}"] for split in SPLITS}

    def prepare_data(self) -> None:
        if self.generated:  # simulated once, cached for every later setup
            self.source.clips(self._sizes(), self.cache_dir)

    def setup(self, stage: str | None = None) -> None:
        if stage == "predict":  # every clip of the input, the trained model's normalisation
            if "predict" not in self.datasets:
                if not self.predicts:
                    raise ValueError(f"data.source._target_={class_path(type(self.source))}: has no prediction set")
                normalizer = self.predict_normalizer(self.source.where())
                self.datasets.update(clip_datasets({"predict": self.source.predict_clips()}, normalizer))
            return
        if all(split in self.datasets for split in SPLITS):
            return
        h, where = self.hparams, self.source.where()
        parts = self._splits(self.source.clips(self._sizes(), self.cache_dir))
        if getattr(self.source, "FIT_ON_FILE", False):
            self._fit(parts["train"], where)
        if h.train_len is not None:
            if h.train_len > (steps := parts["train"].states.shape[1]):
                raise ValueError(f"data.train_len={h.train_len}: longer than the training clips ({steps} steps)")
            parts["train"] = parts["train"].crop(h.train_len)
        if not self.generated:
            parts = capped(parts, self._sizes())
        self._fit(parts["train"], where)
        self.datasets.update(clip_datasets(parts, self.normalizer))
        _, steps, agents, _ = parts["test"].states.shape
        log.info("%s: %s clips of %d steps, %d agents%s", where, {s: len(d) for s, d in self.datasets.items()}, steps,
                 agents, "" if parts["test"].edges is None else ", with edges")

    def _splits(self, parts: dict[str, Clips]) -> dict[str, Clips]:
        """The source's parts as train, val and test: one part split by fractions, a missing validation split carved
        from the training clips; every split non-empty, with the training clips' agents."""
        h = self.hparams
        if set(parts) == {"all"}:
            clips = parts["all"]
            parts = {split: clips.select(idx) for split, idx in split_indices(len(clips), h.split, h.seed).items()}
        elif "val" not in parts:
            keep, val = carve(len(parts["train"]), h.val_fraction, h.seed)
            parts = {**parts, "train": parts["train"].select(keep), "val": parts["train"].select(val)}
        agents = parts["train"].states.shape[2:]
        for split in SPLITS:
            if len(parts[split]) == 0:
                raise ValueError(f"{self.source.where()}: the {split} split has no clips")
            if parts[split].states.shape[2:] != agents:  # clip lengths may differ between files, agents not
                raise ValueError(f"{self.source.where()}: the {split} clips have {parts[split].states.shape[2]} "
                                 f"agents, the training clips {agents[0]}")
        return {split: parts[split] for split in SPLITS}

    def _fit(self, train: Clips, where: str) -> None:
        """The normaliser fitted on ``train`` (once; a trained model's, given by ``use_normalizer``, is kept)."""
        try:
            self.normalizer = self.train_normalizer(lambda: fit_ranges(train, self.hparams.normalization))
        except ValueError as e:  # e.g. no present agent, or agents that never move: a zero range
            raise ValueError(f"{where}: cannot fit the normalisation on the training clips: {e}") from None
