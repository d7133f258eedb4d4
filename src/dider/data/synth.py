"""LightningDataModule for the synthetic 3-particle push system: generated once, cached, normalised."""

from __future__ import annotations

import logging
import math
import numbers
from pathlib import Path

import torch

from dider.data.batch import Normalizer
from dider.data.cache import cache_key, load_or_build
from dider.data.common import SPLITS, ClipDataModule, ClipDataset, check_counts, default_cache_dir
from dider.data.simulate import simulate_push

log = logging.getLogger(__name__)

# ClipDataset and default_cache_dir live in common.py (shared with the real-data modules); re-exported.
__all__ = ["SPLITS", "ClipDataset", "SynthDataModule", "default_cache_dir"]


class SynthDataModule(ClipDataModule):
    """Push-system clips with ground-truth per-step directed edges.

    Each split has its own generator seed derived from ``seed``, so changing ``num_test`` never changes
    the training clips. Generated splits are cached under ``cache_dir`` keyed by every generator
    parameter, written atomically.
    """

    def __init__(
        self,
        num_train: int = 40000,
        num_val: int = 1000,
        num_test: int = 1000,
        num_steps: int = 50,
        burn_in: int = 5,
        push_factor: float = 0.05,
        batch_size: int = 16,
        eval_batch_size: int = 256,
        num_workers: int = 0,
        pin_memory: bool = False,
        seed: int = 1,
        cache_dir: str | None = None,
        horizons: tuple[int, ...] = (1, 15, 25),
        burn_in_mode: str = "global",
    ) -> None:
        super().__init__()
        # Counts must be integers here, not only large enough (bools and floats such as 1.5 are rejected).
        for key, value in [("num_train", num_train), ("num_val", num_val), ("num_test", num_test),
                           ("num_steps", num_steps), ("burn_in", burn_in), ("batch_size", batch_size),
                           ("eval_batch_size", eval_batch_size), ("num_workers", num_workers)]:
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise ValueError(f"data.{key}={value!r}: must be an integer")
        check_counts(num_train=(num_train, 1), num_val=(num_val, 1), num_test=(num_test, 1),
                     num_steps=(num_steps, 2))
        if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or not abs(seed) < 2**53:
            raise ValueError(f"data.seed={seed!r}: must be an integer of magnitude < 2**53")
        if isinstance(push_factor, bool) or not isinstance(push_factor, (int, float)) or not math.isfinite(push_factor):
            raise ValueError(f"data.push_factor={push_factor!r}: must be a finite number")
        self.save_hyperparameters(logger=False)
        self.init_shared(num_steps, length_key="data.num_steps", integer_horizons=True)

    def _split_params(self, split: str) -> dict:
        h = self.hparams
        size = {"train": h.num_train, "val": h.num_val, "test": h.num_test}[split]
        return {"kind": "push", "split": split, "num_samples": size, "num_steps": h.num_steps,
                "push_factor": h.push_factor, "seed": h.seed * 1000 + SPLITS.index(split), "version": 1}

    def _path(self, split: str) -> Path:
        return self.cache_dir / f"synth_{split}_{cache_key(self._split_params(split))}.pt"

    def _generate(self, split: str) -> dict:
        p = self._split_params(split)
        log.info("generating %d synthetic %s clips -> %s", p["num_samples"], split, self._path(split))
        states, edges = simulate_push(p["num_samples"], p["num_steps"], p["push_factor"], seed=p["seed"])
        return {"states": states, "edges": edges, "params": p}

    def prepare_data(self) -> None:
        for split in SPLITS:
            if not self._path(split).exists():
                load_or_build(self._path(split), lambda split=split: self._generate(split))

    def setup(self, stage: str | None = None) -> None:
        if self.datasets:
            return
        raw = {split: load_or_build(self._path(split), lambda split=split: self._generate(split)) for split in SPLITS}
        self.normalizer = Normalizer.fit(raw["train"]["states"])
        for split, blob in raw.items():
            states = self.normalizer.normalize(blob["states"])
            mask = torch.ones(states.shape[:3], dtype=torch.bool)
            # edges[t] produced state t from t-1, so the transition t -> t+1 is labelled by edges[t+1].
            self.datasets[split] = ClipDataset(states, mask, blob["edges"][:, 1:])
