"""LightningDataModule for the synthetic 3-particle push system: generated once, cached, normalised."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import torch

from dider.data.batch import Normalizer
from dider.data.cache import cache_key, load_or_build
from dider.data.common import SPLITS, ClipDataModule, ClipDataset, default_cache_dir
from dider.data.loader import Loader
from dider.data.simulate import PUSH_SHAPES, simulate_push
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
        burn_in: int = 5,
        push_factor: float = 0.05,
        loader: Mapping[str, Any] | None = None,
        seed: int = 1,
        cache_dir: str | None = None,
        horizons: tuple[int, ...] = (1, 15, 25),
        burn_in_mode: str = "global",
        push: str = "linear",
    ) -> None:
        """seed: the data seed (the top-level ``seed`` drives the model and training). push: the push's shape inside
        the radius, ``linear`` (DNRI's: fading in and out) or ``step`` (on and off at once: a positive control for
        segment boundaries; :func:`~dider.data.simulate.simulate_push`)."""
        super().__init__()
        check_settings(self, locals(), key="data")
        self.save_hyperparameters(logger=False)
        self.init_shared(num_steps, length_key="data.num_steps", integer_horizons=True)

    def _split_params(self, split: str) -> dict:
        h = self.hparams
        size = {"train": h.num_train, "val": h.num_val, "test": h.num_test}[split]
        shape = {} if h.get("push", "linear") == "linear" else {"push": h.push}  # the linear push's caches stay valid
        return {"kind": "push", "split": split, "num_samples": size, "num_steps": h.num_steps,
                "push_factor": h.push_factor, "seed": h.seed * 1000 + SPLITS.index(split), "version": 1, **shape}

    def _path(self, split: str) -> Path:
        return self.cache_dir / f"synth_{split}_{cache_key(self._split_params(split))}.pt"

    def _generate(self, split: str) -> dict:
        p = self._split_params(split)
        log.info("generating %d synthetic %s clips -> %s", p["num_samples"], split, self._path(split))
        states, edges = simulate_push(p["num_samples"], p["num_steps"], p["push_factor"], seed=p["seed"],
                                      shape=p.get("push", "linear"))
        return {"states": states, "edges": edges, "params": p}

    def prepare_data(self) -> None:
        for split in SPLITS:
            if not self._path(split).exists():
                load_or_build(self._path(split), lambda split=split: self._generate(split))

    def setup(self, stage: str | None = None) -> None:
        if self.datasets:
            return
        raw = {split: load_or_build(self._path(split), lambda split=split: self._generate(split)) for split in SPLITS}
        self.normalizer = self.train_normalizer(lambda: Normalizer.fit(raw["train"]["states"]))
        for split, blob in raw.items():
            states = self.normalizer.normalize(blob["states"])
            mask = torch.ones(states.shape[:3], dtype=torch.bool)
            # edges[t] produced state t from t-1, so the transition t -> t+1 is labelled by edges[t+1].
            self.datasets[split] = ClipDataset(states, mask, blob["edges"][:, 1:])
