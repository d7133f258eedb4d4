"""LightningDataModule for NRI's particle systems: simulated (``data=springs``, ``data=charged``) or read from NRI's
``.npy`` files (``data=nri_files``), with ground-truth edges per step.

Both paths give the same batches: states [B, T, N, 4] (x, y, vx, vy) normalised as NRI does (positions and
velocities each mapped to [-1, 1] by the training split's scalar min and max), mask [B, T, N] (all True), edges
[B, T-1, E] long (the transitions t -> t+1; rows receive, as in the files) and source ``clip`` [B].
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import torch

from dider.data.batch import Normalizer
from dider.data.common import SPLITS, ClipDataModule, ClipDataset, spread_indices
from dider.data.loader import Loader
from dider.data.nri_files import read_nri_split
from dider.data.readers import particles
from dider.data.readers.particles import Simulation
from dider.protocol import check_horizons
from dider.validation import Rule, check_settings, integer, optional

log = logging.getLogger(__name__)


class NRIDataModule(ClipDataModule):
    """NRI's springs or charged particles (module docstring). With ``simulate`` the clips are generated (each split
    from its own seed, cached under ``cache_dir`` by every setting that made them) and ``num_train`` / ``num_val``
    / ``num_test`` are the split sizes; with ``root`` they are read from NRI's files and those cap each split."""

    SETTINGS: ClassVar[dict[str, Rule | type]] = ClipDataModule.SETTINGS | {
        "simulate": Simulation, "root": optional(lambda v: None if isinstance(v, str) and v else "expected a path"),
        "suffix": lambda v: None if isinstance(v, str) else "expected a string",
    }
    LOADER = Loader(batch_size=32, eval_batch_size=256)
    SIMULATE = Simulation()

    def __init__(
        self,
        simulate: Mapping[str, Any] | None = None,
        root: str | None = None,
        suffix: str = "_springs5",
        num_train: int | None = None,
        num_val: int | None = None,
        num_test: int | None = None,
        burn_in: int = 29,
        horizons: Sequence[int] = (1, 10, 20),
        burn_in_mode: str = "global",
        loader: Mapping[str, Any] | None = None,
        cache_dir: str | None = None,
    ) -> None:
        """simulate: the simulation's settings (:class:`Simulation`), or null to read ``root``. root: a folder of
        NRI's files (:mod:`dider.data.nri_files`), named ``{loc,vel,edges}_{train,valid,test}{suffix}.npy``."""
        super().__init__()
        sizes = {"num_train": num_train, "num_val": num_val, "num_test": num_test}
        both = lambda v: "give data.root or data.simulate, not both" if v and simulate is not None else None  # noqa: E731
        related = {"root": (root, both)}
        if simulate is not None:
            related |= {f"{k}": (v, integer(1, " (the simulated split's size)")) for k, v in sizes.items()}
        check_settings(self, locals(), related, key="data")
        self.save_hyperparameters(logger=False)
        self.simulation = None if simulate is None else Simulation(**dict(simulate))
        frames = None if simulate is None else self.simulation.num_frames  # files: checked in setup
        self.init_shared(frames, length_key="data.simulate.num_frames", integer_horizons=True)

    def _simulated(self, split: str) -> tuple[torch.Tensor, torch.Tensor]:
        clips = particles.read(self.simulation, {split: getattr(self.hparams, f"num_{split}")}, self.cache_dir)[split]
        return clips.states, clips.edges

    def _read(self, split: str) -> tuple[torch.Tensor, torch.Tensor]:
        if not self.hparams.root:
            raise ValueError("data.root is not set: point it at a folder of NRI's .npy files (or set data.simulate)")
        root = Path(self.hparams.root).expanduser()
        if not root.is_dir():
            raise FileNotFoundError(f"data.root={root}: no such folder")
        states, edges = read_nri_split(root, split, self.hparams.suffix)
        check_horizons(self.hparams.horizons, states.shape[1], self.hparams.burn_in,
                       where=f" in {root} ({split}: {states.shape[1]} frames)")
        return states, edges

    def prepare_data(self) -> None:
        if self.simulation is not None:
            for split in SPLITS:
                self._simulated(split)

    def setup(self, stage: str | None = None) -> None:
        if all(s in self.datasets for s in SPLITS):
            return
        raw = {split: self._simulated(split) if self.simulation else self._read(split) for split in SPLITS}
        self.normalizer = self.train_normalizer(lambda: Normalizer.fit(raw["train"][0]))
        caps = {"train": self.hparams.num_train, "val": self.hparams.num_val, "test": self.hparams.num_test}
        for split, (states, edges) in raw.items():
            idx = spread_indices(len(states), None if self.simulation else caps[split])
            clips = states[idx]
            self.datasets[split] = ClipDataset(self.normalizer.normalize(clips),
                                               torch.ones(clips.shape[:3], dtype=torch.bool), edges[idx], {"clip": idx})
        log.info("%s: %s clips, %d balls, %d frames", self.simulation.system if self.simulation else self.hparams.root,
                 {s: len(d) for s, d in self.datasets.items()}, raw["train"][0].shape[2], raw["train"][0].shape[1])
