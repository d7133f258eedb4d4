"""NRI's particle systems as a clip source (``data=springs``, ``data=charged``): each split simulated from its own
seed (:func:`~dider.data.particles.simulate_particles`), cached under the cache folder by every setting that made
it. Edges come receiver-major as in NRI's files, one per transition t -> t+1."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any, Protocol

import torch

from dider.data.cache import cache_key, cached_splits
from dider.data.common import SPLITS
from dider.data.particles import simulate_particles
from dider.data.tracks import Clips
from dider.graph import edge_index

log = logging.getLogger(__name__)


class Simulated(Protocol):
    """The settings (``dider.data.nri.Simulation``); their field names are part of every cache key."""

    system: str
    num_balls: int
    num_frames: int
    sample_every: int
    switch_prob: float
    seed: int


def cache_path(sim: Simulated, split: str, size: int, cache_dir: Path) -> Path:
    params = {**asdict(sim), "split": split, "num_samples": size, "version": 1}
    return cache_dir / f"{sim.system}_{split}_{cache_key(params)}.pt"


def read(sim: Simulated, sizes: Mapping[str, int], cache_dir: Path) -> dict[str, Clips]:
    """Each split of ``sizes`` (split -> number of clips), from the cache or simulated and cached."""

    def build(split: str, size: int, path: Path) -> dict[str, Any]:
        log.info("simulating %d %s clips of %s (%d balls) -> %s", size, split, sim.system, sim.num_balls, path)
        loc, vel, edges = simulate_particles(sim.system, size, sim.num_frames, sim.num_balls, sim.sample_every,
                                             sim.switch_prob, seed=sim.seed * 1000 + SPLITS.index(split))
        send, recv = edge_index(sim.num_balls)
        states = torch.cat([loc, vel], dim=2).transpose(2, 3).float()  # [S, T, N, 4]
        return {"states": states.contiguous(), "edges": edges[:, 1:, recv, send].contiguous()}

    blobs = cached_splits(sizes, lambda split, size: cache_path(sim, split, size, cache_dir), build)
    return {split: Clips(b["states"], edges=b["edges"]) for split, b in blobs.items()}
