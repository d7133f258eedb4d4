"""LightningDataModule for the synthetic 3-particle push system: generated once, cached, normalised."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

from dider.data.batch import Normalizer
from dider.data.clip_splits import clip_datasets
from dider.data.common import SPLITS, ClipDataModule, ClipDataset, default_cache_dir
from dider.data.loader import Loader
from dider.data.readers import push
from dider.data.simulate import PUSH_SHAPES
from dider.validation import Rule, check_settings, finite, integer, one_of

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
        "num_train": integer(1), "num_val": integer(1), "num_test": integer(1), "num_steps": integer(2),
        "push_factor": finite, "seed": integer(-(2**53) + 1, " (magnitude < 2**53)", 2**53 - 1),
        "push": one_of(*PUSH_SHAPES),
    }
    LOADER = Loader(batch_size=16, eval_batch_size=256)

    def __init__(
        self,
        num_train: int = 40000,
        num_val: int = 1000,
        num_test: int = 1000,
        num_steps: int = 50,
        push_factor: float = 0.05,
        loader: Mapping[str, Any] | None = None,
        seed: int = 1,
        cache_dir: str | None = None,
        push: str = "linear",
    ) -> None:
        """seed: the data seed (the top-level ``seed`` drives the model and training). push: the push's shape inside
        the radius, ``linear`` (DNRI's: fading in and out) or ``step`` (on and off at once: a positive control for
        segment boundaries; :func:`~dider.data.simulate.simulate_push`)."""
        super().__init__()
        check_settings(self, locals(), key="data")
        self.save_hyperparameters(logger=False)
        self.init_shared()

    def _source(self) -> tuple[push.Settings, dict[str, int]]:
        h = self.hparams
        settings = push.Settings(h.num_steps, h.push_factor, h.get("push", "linear"), h.seed)
        return settings, {"train": h.num_train, "val": h.num_val, "test": h.num_test}

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
