"""LightningDataModule for the synthetic 3-particle push system: generated once, cached, normalised."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any, ClassVar

from dider.data.batch import Normalizer
from dider.data.clip_splits import clip_datasets
from dider.data.common import SPLITS, ClipDataModule, ClipDataset, default_cache_dir, source_node
from dider.data.loader import Loader
from dider.data.readers import push
from dider.validation import Rule, check_settings, integer

log = logging.getLogger(__name__)

# ClipDataset and default_cache_dir live in common.py (shared with the real-data modules); re-exported.
__all__ = ["SPLITS", "ClipDataset", "SynthDataModule", "default_cache_dir"]


class SynthDataModule(ClipDataModule):
    """Push-system clips with ground-truth per-step directed edges.

    Each split has its own generator seed derived from ``seed``, so changing ``num_test`` never changes
    the training clips. Generated splits are cached under ``cache_dir`` keyed by every generator
    parameter, written atomically.
    """

    SETTINGS: ClassVar[dict[str, Rule | type]] = ClipDataModule.SETTINGS | {
        "num_train": integer(1), "num_val": integer(1), "num_test": integer(1), "source": push.Settings}
    LOADER = Loader(batch_size=16, eval_batch_size=256)
    SOURCE = push.Settings()  # the simulation's defaults; data.source overrides them key by key

    def __init__(
        self,
        source: Mapping[str, Any] | None = None,
        num_train: int = 40000,
        num_val: int = 1000,
        num_test: int = 1000,
        loader: Mapping[str, Any] | None = None,
        cache_dir: str | None = None,
    ) -> None:
        """source: the simulation (:class:`~dider.data.readers.push.Settings`): ``num_steps`` frames per clip,
        ``push_factor``, the ``push``'s shape and the data ``seed``. num_train, num_val, num_test: the split sizes."""
        super().__init__()
        check_settings(self, locals(), key="data")
        self.source = source_node(self.SOURCE, source)
        self.save_hyperparameters(logger=False)
        self.hparams["source"] = asdict(self.source)  # as simulated
        self.init_shared()

    def _source(self) -> tuple[push.Settings, dict[str, int]]:
        h = self.hparams
        return self.source, {"train": h.num_train, "val": h.num_val, "test": h.num_test}

    def _path(self, split: str) -> Path:
        settings, sizes = self._source()
        return push.cache_path(settings, split, sizes[split], self.cache_dir)

    def prepare_data(self) -> None:
        settings, sizes = self._source()
        missing = {s: n for s, n in sizes.items() if not push.cache_path(settings, s, n, self.cache_dir).exists()}
        push.read(settings, missing, self.cache_dir)

    def setup(self, stage: str | None = None) -> None:
        if self.datasets:
            return
        raw = push.read(*self._source(), self.cache_dir)
        self.normalizer = self.train_normalizer(lambda: Normalizer.fit(raw["train"].states))
        self.datasets.update(clip_datasets(raw, self.normalizer))
