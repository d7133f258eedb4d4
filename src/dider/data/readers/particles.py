"""NRI's particle systems as a clip source (``data=springs``, ``data=charged``): each split simulated from its own
seed (:func:`~dider.data.particles.simulate_particles`), cached under the cache folder by every setting that made
it. Edges come receiver-major as in NRI's files, one per transition t -> t+1; ids: ``clip``, the clip's index."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, ClassVar

import torch

from dider.data.cache import cache_key, cached_splits
from dider.data.clip_source import Clips
from dider.data.common import SPLITS
from dider.data.particles import SYSTEMS, simulate_particles
from dider.graph import edge_index
from dider.validation import Rule, check_settings, integer, one_of, within

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Simulation:
    """What ``data=springs`` / ``data=charged`` simulate (:func:`~dider.data.particles.simulate_particles`): their
    ``data.source`` node; the split sizes are ``data.num_train``, ``num_val`` and ``num_test``."""

    reader: str = "particles"  # simulated (data=nri_files reads NRI's files: dider.data.readers.nri_files)
    system: str = "springs"  # springs or charged
    num_balls: int = 5
    num_frames: int = 49  # frames per clip (NRI: 49 for training, 99 in its test files)
    sample_every: int = 100  # integration steps per frame
    switch_prob: float = 0.0  # chance per frame that a spring breaks or forms / a charge flips (0: NRI's static graph)
    seed: int = 1  # the data seed; each split draws from its own stream

    GENERATED: ClassVar[bool] = True  # data.num_* are the splits' sizes

    SETTINGS: ClassVar[dict[str, Rule]] = {
        "reader": one_of("particles"), "system": one_of(*SYSTEMS), "num_balls": integer(2), "num_frames": integer(2),
        "sample_every": integer(1), "switch_prob": within(0.0, 1.0), "seed": integer(0, "", 2**31 - 1)}

    def __post_init__(self) -> None:
        check_settings(self, asdict(self), key="data.source")

    def clips(self, sizes: Mapping[str, int], cache_dir: Path) -> dict[str, Clips]:
        return read(self, sizes, cache_dir)

    def where(self) -> str:
        return f"the {self.system} simulation"


CLIPS = Simulation  # a clip source: data.source.reader=particles


def cache_path(sim: Simulation, split: str, size: int, cache_dir: Path) -> Path:
    # every setting but the reader's name, which the files' names predate
    params = {**{k: v for k, v in asdict(sim).items() if k != "reader"}, "split": split, "num_samples": size,
              "version": 1}
    return cache_dir / f"{sim.system}_{split}_{cache_key(params)}.pt"


def read(sim: Simulation, sizes: Mapping[str, int], cache_dir: Path) -> dict[str, Clips]:
    """Each split of ``sizes`` (split -> number of clips), from the cache or simulated and cached."""

    def build(split: str, size: int, path: Path) -> dict[str, Any]:
        log.info("simulating %d %s clips of %s (%d balls) -> %s", size, split, sim.system, sim.num_balls, path)
        loc, vel, edges = simulate_particles(sim.system, size, sim.num_frames, sim.num_balls, sim.sample_every,
                                             sim.switch_prob, seed=sim.seed * 1000 + SPLITS.index(split))
        send, recv = edge_index(sim.num_balls)
        states = torch.cat([loc, vel], dim=2).transpose(2, 3).float()  # [S, T, N, 4]
        return {"states": states.contiguous(), "edges": edges[:, 1:, recv, send].contiguous()}

    blobs = cached_splits(sizes, lambda split, size: cache_path(sim, split, size, cache_dir), build)
    return {split: Clips(b["states"], edges=b["edges"], ids={"clip": torch.arange(len(b["states"]))})
            for split, b in blobs.items()}
