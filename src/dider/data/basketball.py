"""Basketball player trajectories as a data module (the files and their reader:
:mod:`dider.data.readers.basketball`). DNRI's setting is the default: the 5 offence players of Zhan et al.'s files
(its forecast protocol, ``conf/protocol/basketball.yaml``: 40 burn-in steps + 9 predicted, horizons 1/5/9).

The validation split is carved from the training file with a seeded permutation (``val_fraction``,
``seed``) when the files have none. Positions and velocities are normalised with the scalar min/max of
the training split (DNRI's scheme). All agents are present at every step (mask all True); no edges.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import asdict
from typing import Any, ClassVar

import torch

from dider.data.batch import Normalizer
from dider.data.clip_splits import capped, clip_datasets
from dider.data.common import ClipDataModule, source_node
from dider.data.loader import Loader
from dider.data.readers import basketball
from dider.data.tracks import Clips
from dider.validation import Rule, check_settings, integer, optional, within_open

log = logging.getLogger(__name__)


def carve(num: int, fraction: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Reproducible (keep, carved) index split of range(num): ``round(fraction * num)`` (>= 1) carved."""
    take = max(1, round(fraction * num))
    if take >= num:
        raise ValueError(f"data.val_fraction={fraction}: carving {take} of {num} training clips leaves none")
    perm = torch.randperm(num, generator=torch.Generator().manual_seed(seed))
    return perm[take:].sort().values, perm[:take].sort().values


class BasketballDataModule(ClipDataModule):
    """Basketball clips: states [B, T, N, 4] normalised, mask [B, T, N] all True (see the module docstring).

    After ``setup``: ``normalizer``, ``datasets`` (ClipDataset per split), ``format`` ('zhan' or 'dnri').
    ``cache_dir`` is accepted for a uniform interface; loading the arrays is fast, so nothing is cached.
    """

    units = "ft"

    SETTINGS: ClassVar[dict[str, Rule | type]] = ClipDataModule.SETTINGS | {
        "val_fraction": within_open(0, 1), "train_len": optional(integer(2))}
    LOADER = Loader(batch_size=128, eval_batch_size=128)  # DNRI's basketball batch
    SOURCE = basketball.BasketballFiles()  # data.source overrides it key by key

    def __init__(
        self,
        source: Mapping[str, Any] | None = None,
        val_fraction: float = 0.1,
        seed: int = 1,
        train_len: int | None = None,
        num_train: int | None = None,
        num_val: int | None = None,
        num_test: int | None = None,
        loader: Mapping[str, Any] | None = None,
        cache_dir: str | None = None,
    ) -> None:
        """source: the files (:class:`~dider.data.readers.basketball.BasketballFiles`): ``root`` (required),
        ``format``, ``agents``, ``frame_rate``.
        val_fraction: the training clips carved off for validation when the files have no validation split.
        seed: the carving seed.
        train_len: crop training clips to their first steps (DNRI trains on 40); null: whole clips."""
        super().__init__()
        check_settings(self, locals(), key="data")
        self.source = source_node(self.SOURCE, source)
        self.save_hyperparameters(logger=False)
        self.hparams["source"] = asdict(self.source)  # as read
        self.init_shared()
        self.format: str | None = None

    def _read(self) -> dict[str, Clips]:
        """Raw clips per split, in feet (and feet / s or the file's velocity units), validation carved from the
        training file where the files have none."""
        h, src = self.hparams, self.source
        self.format, raw = basketball.read(src.root, src.format, src.agents, src.frame_rate)
        train = raw["train"]
        if "val" not in raw:  # carve validation clips from train, reproducibly
            keep, val = carve(len(train), h.val_fraction, h.seed)
            raw["train"], raw["val"] = train.select(keep), train.select(val)
        for split, clips in raw.items():
            if clips.states.shape[2:] != train.states.shape[2:]:  # clip lengths may differ between files, agents not
                raise ValueError(f"basketball {split} clips have {clips.states.shape[2]} agents, train "
                                 f"{train.states.shape[2]}")
            if len(clips) == 0:
                raise ValueError(f"basketball {split} split has no clips ({src.root})")
        return {s: raw[s] for s in ("train", "val", "test")}

    def setup(self, stage: str | None = None) -> None:
        if self.datasets:
            return
        h = self.hparams
        raw = self._read()
        if h.train_len is not None:
            if h.train_len > raw["train"].states.shape[1]:
                raise ValueError(f"data.train_len={h.train_len}: longer than the training clips "
                                 f"({raw['train'].states.shape[1]} steps)")
            raw["train"] = raw["train"].crop(h.train_len)
        raw = capped(raw, {"train": h.num_train, "val": h.num_val, "test": h.num_test})
        try:
            self.normalizer = self.train_normalizer(lambda: Normalizer.fit(raw["train"].states))
        except ValueError as err:  # e.g. constant positions: nothing to scale by
            raise ValueError(f"basketball training clips in data.source.root={self.source.root}: {err}") from err
        self.datasets.update(clip_datasets(raw, self.normalizer))
        test = raw["test"].states
        log.info("basketball (%s): %s clips of %s steps, %d agents", self.format,
                 {s: len(d) for s, d in self.datasets.items()}, test.shape[1], test.shape[2])
