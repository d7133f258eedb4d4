"""Bring-your-own trajectories: one ``.npz`` file (``data.source.path``) of fixed-length multi-agent clips (the layout
and its reader: :mod:`dider.data.readers.trajectories`).

Clips are split into train / val / test with a seeded permutation (``split`` fractions, ``seed``);
min/max normalisation is fitted on the present agents of the train split; absent agents get zeros.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any, ClassVar

import torch

from dider.data.batch import Normalizer
from dider.data.clip_splits import capped, clip_datasets
from dider.data.common import ClipDataModule, source_node
from dider.data.readers import trajectories
from dider.validation import Rule, check_settings

log = logging.getLogger(__name__)


def split_indices(num: int, fractions: Sequence[float], seed: int) -> dict[str, torch.Tensor]:
    """Seeded train / val / test index sets of range(num); val and test get >= 1 clip each."""
    if len(fractions) != 3 or min(fractions) <= 0 or abs(sum(fractions) - 1) > 1e-6:
        raise ValueError(f"data.split={list(fractions)}: three positive fractions (train, val, test) "
                         f"summing to 1")
    val, test = (max(1, round(f * num)) for f in fractions[1:])
    if num - val - test < 1:
        raise ValueError(f"data.split={list(fractions)}: {num} clips are too few for train, val and test")
    perm = torch.randperm(num, generator=torch.Generator().manual_seed(seed))
    parts = {"train": perm[val + test:], "val": perm[:val], "test": perm[val:val + test]}
    return {k: v.sort().values for k, v in parts.items()}


class TrajectoryDataModule(ClipDataModule):
    """Clips from a user's npz (see the module docstring). Batches: states [B, T, N, 4] normalised,
    mask [B, T, N] bool, and edges [B, T-1, E] long when the file has them.

    After ``setup``: ``normalizer``, ``datasets`` (ClipDataset per split). ``cache_dir`` is accepted for a
    uniform interface; nothing is cached (loading one npz is fast).
    """

    predicts = True

    SETTINGS: ClassVar[dict[str, Rule | type]] = ClipDataModule.SETTINGS
    SOURCE = trajectories.NpzFile()  # data.source overrides it key by key

    def __init__(
        self,
        source: Mapping[str, Any] | None = None,
        split: Sequence[float] = (0.8, 0.1, 0.1),
        seed: int = 1,
        num_train: int | None = None,
        num_val: int | None = None,
        num_test: int | None = None,
        loader: Mapping[str, Any] | None = None,
        cache_dir: str | None = None,
    ) -> None:
        """source: the file (:class:`~dider.data.readers.trajectories.NpzFile`): its ``path`` (required) and
        ``frame_rate`` (finite-difference velocities = (pos[t] - pos[t-1]) * frame_rate, a file without 'velocities').
        split: train / val / test fractions of the clips (a permutation seeded by ``seed``)."""
        super().__init__()
        check_settings(self, locals(), key="data")
        self.source = source_node(self.SOURCE, source)
        split_indices(10**6, split, seed)  # the form of split; the clip count is known in setup
        self.save_hyperparameters(logger=False)
        self.hparams["source"] = asdict(self.source)  # as read
        self.init_shared()

    def setup(self, stage: str | None = None) -> None:
        if self.datasets:
            return
        h, src = self.hparams, self.source
        if stage == "predict":  # every clip, no split, the trained model's normalisation
            clips = trajectories.read(src.path, src.frame_rate)
            normalizer = self.predict_normalizer(f"data.source.path={Path(src.path).expanduser()}")
            self.datasets.update(clip_datasets({"predict": clips}, normalizer))
            return
        clips = trajectories.read(src.path, src.frame_rate)
        path = Path(src.path).expanduser()
        parts = {s: clips.select(idx) for s, idx in split_indices(len(clips), h.split, h.seed).items()}
        parts = capped(parts, {"train": h.num_train, "val": h.num_val, "test": h.num_test})
        train = parts["train"]
        try:
            self.normalizer = self.train_normalizer(lambda: Normalizer.fit(train.states, train.mask))
        except ValueError as e:  # e.g. no present agent, or agents that never move
            raise ValueError(f"{path}: cannot fit the normalisation on the train split: {e}") from None
        self.datasets.update(clip_datasets(parts, self.normalizer))
        _, t, n, _ = clips.states.shape
        log.info("trajectories %s: %s clips, %d steps, %d agents%s", path,
                 {s: len(d) for s, d in self.datasets.items()}, t, n, "" if clips.edges is None else ", with edges")
