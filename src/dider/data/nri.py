"""LightningDataModule for NRI's particle systems: simulated (``data=springs``, ``data=charged``) or read from NRI's
``.npy`` files (``data=nri_files``), with ground-truth edges per step.

Both paths give the same batches: states [B, T, N, 4] (x, y, vx, vy) normalised as NRI does (positions and
velocities each mapped to [-1, 1] by the training split's scalar min and max), mask [B, T, N] (all True), edges
[B, T-1, E] long (the transitions t -> t+1; rows receive, as in the files) and source ``clip`` [B].
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import asdict
from typing import Any, ClassVar

from dider.data.batch import Normalizer
from dider.data.clip_splits import capped, clip_datasets
from dider.data.common import SPLITS, ClipDataModule, source_node
from dider.data.loader import Loader
from dider.data.readers import nri_files, particles
from dider.data.readers.particles import NRIFiles, Simulation
from dider.data.tracks import Clips
from dider.validation import ConfigError, Rule, check_settings, integer

log = logging.getLogger(__name__)


class NRIDataModule(ClipDataModule):
    """NRI's springs or charged particles (module docstring). Simulated (``source.reader: particles``) the clips are
    generated, each split from its own seed, cached under ``cache_dir`` by every setting that made them, and
    ``num_train`` / ``num_val`` / ``num_test`` are the split sizes; read from NRI's files (``source.reader:
    nri_files``) those cap each split."""

    SETTINGS: ClassVar[dict[str, Rule | type]] = ClipDataModule.SETTINGS
    LOADER = Loader(batch_size=32, eval_batch_size=256)
    SOURCES = {"particles": Simulation, "nri_files": NRIFiles}

    def __init__(
        self,
        source: Mapping[str, Any] | None = None,
        num_train: int | None = None,
        num_val: int | None = None,
        num_test: int | None = None,
        loader: Mapping[str, Any] | None = None,
        cache_dir: str | None = None,
    ) -> None:
        """source: the simulation (:class:`~dider.data.readers.particles.Simulation`, ``reader: particles``, the
        default) or NRI's files (:class:`~dider.data.readers.particles.NRIFiles`, ``reader: nri_files``: ``root``,
        ``suffix``)."""
        super().__init__()
        given = dict(source or {})
        cls = self.SOURCES.get(given.get("reader", "particles"))
        if cls is None:
            raise ConfigError(f"data.source.reader={given['reader']!r}: expected one of {sorted(self.SOURCES)}")
        self.source = source_node(cls(), given)
        sizes = {"num_train": num_train, "num_val": num_val, "num_test": num_test}
        related = {k: (v, integer(1, " (the simulated split's size)")) for k, v in sizes.items()} \
            if cls is Simulation else {}
        check_settings(self, locals(), related, key="data")
        self.save_hyperparameters(logger=False)
        self.hparams["source"] = asdict(self.source)  # as read
        self.simulation = self.source if cls is Simulation else None
        self.init_shared()

    def _read(self) -> dict[str, Clips]:
        h = self.hparams
        if self.simulation is not None:
            return particles.read(self.simulation, {s: getattr(h, f"num_{s}") for s in SPLITS}, self.cache_dir)
        return nri_files.read(self.source.root, self.source.suffix)

    def prepare_data(self) -> None:
        if self.simulation is not None:
            self._read()

    def setup(self, stage: str | None = None) -> None:
        if all(s in self.datasets for s in SPLITS):
            return
        raw = self._read()
        # NRI fits the ranges on the whole training file; read from files, num_* then cap each split
        self.normalizer = self.train_normalizer(lambda: Normalizer.fit(raw["train"].states))
        h = self.hparams
        caps = {} if self.simulation else {"train": h.num_train, "val": h.num_val, "test": h.num_test}
        self.datasets.update(clip_datasets(capped(raw, caps), self.normalizer))
        train = raw["train"].states
        log.info("%s: %s clips, %d balls, %d frames", self.simulation.system if self.simulation else self.source.root,
                 {s: len(d) for s, d in self.datasets.items()}, train.shape[2], train.shape[1])
