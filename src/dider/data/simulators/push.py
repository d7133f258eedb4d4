"""The 3-particle "push" system, the synthetic data set of the DNRI paper, and its clip source (``data=synth``).

Particles 0 and 1 move at constant velocity; particle 2 is pushed away from particle i whenever it is
within distance 1 of it: v2 += push * (1 - d) * unit(p2 - p_i). All samples advance together, so 40k
clips of 50 steps take well under a second per step of the loop over time. Each split is generated from its own
seed and cached under the cache folder by every setting that made it, so a changed ``num_test`` never changes the
training clips.
"""

from __future__ import annotations

import logging
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import torch

from dider.data.cache import cache_key, cached_splits
from dider.data.clip_source import Clips
from dider.data.common import SPLITS
from dider.data.sources import SourceSettings
from dider.validation import Rule, finite, integer, one_of

log = logging.getLogger(__name__)

# Directed edges in sender-major order for N = 3: (0,1) (0,2) (1,0) (1,2) (2,0) (2,1).
EDGE_0_TO_2 = 1
EDGE_1_TO_2 = 3


PUSH_SHAPES = ("linear", "step")


def simulate_push(
    num_samples: int,
    num_steps: int = 50,
    push_factor: float = 0.05,
    radius: float = 1.0,
    seed: int = 0,
    shape: str = "linear",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Simulate the push system. ``shape``: how the push grows inside the radius: ``linear`` (DNRI's, push_factor *
    (1 - d): it fades in and out smoothly as particle 2 crosses the radius) or ``step`` (push_factor / 3 wherever d <
    radius, the linear push's mean over the unit disc: on and off at once; a positive control for boundaries, which
    then have a discontinuity to land on).

    Returns:
        states: [S, T, 3, 4] float32, (x, y, vx, vy) after each step's update.
        edges:  [S, T, 6] long; edges[:, t] is the force that produced state t from state t-1
            (distances measured on the pre-update positions), as in DNRI's generator.
    """
    for name, value, low in (("num_samples", num_samples, 1), ("num_steps", num_steps, 2)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
            raise ValueError(f"simulate_push: {name}={value!r}: need an integer >= {low}")
    for name, value in (("push_factor", push_factor), ("radius", radius)):
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
            raise ValueError(f"simulate_push: {name}={value!r}: need a finite number")
    if radius <= 0:
        raise ValueError(f"simulate_push: radius={radius!r}: must be > 0")
    if shape not in PUSH_SHAPES:
        raise ValueError(f"simulate_push: shape={shape!r}: expected one of {list(PUSH_SHAPES)}")
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or not -(2**63) <= seed < 2**64:
        raise ValueError(f"simulate_push: seed={seed!r}: need an integer in [-2**63, 2**64)")
    num_samples, num_steps, seed = int(num_samples), int(num_steps), int(seed)
    push_factor, radius = float(push_factor), float(radius)
    g = torch.Generator().manual_seed(seed)

    def uniform(lo: float, hi: float) -> torch.Tensor:
        return lo + (hi - lo) * torch.rand(num_samples, 2, generator=g, dtype=torch.float64)

    pos = torch.stack([uniform(-2, -1), uniform(1, 2), uniform(-1, 1)], dim=1)  # [S, 3, 2]
    vel = torch.stack([uniform(0.05, 0.1), uniform(-0.1, -0.05), uniform(-0.05, 0.05)], dim=1)

    states = torch.empty(num_samples, num_steps, 3, 4, dtype=torch.float64)
    edges = torch.zeros(num_samples, num_steps, 6, dtype=torch.long)
    for t in range(num_steps):
        offset = pos[:, 2:3] - pos[:, :2]  # [S, 2, 2]: particle 2 relative to particles 0 and 1
        dist = offset.norm(dim=-1, keepdim=True)  # [S, 2, 1]
        active = dist < radius
        strength = push_factor * (1 - dist) if shape == "linear" else torch.full_like(dist, push_factor / 3)
        push = torch.where(active, strength * offset / dist.clamp_min(1e-12), 0.0)
        vel[:, 2] += push.sum(dim=1)
        edges[:, t, EDGE_0_TO_2] = active[:, 0, 0].long()
        edges[:, t, EDGE_1_TO_2] = active[:, 1, 0].long()
        pos = pos + vel
        states[:, t, :, :2] = pos
        states[:, t, :, 2:] = vel
    out = states.float()
    if not bool(torch.isfinite(out).all()):
        raise ValueError(f"simulate_push: the states left the float32 range (push_factor={push_factor!r} too large?)")
    return out, edges


@dataclass(frozen=True)
class Push(SourceSettings):
    """What the simulation depends on: ``data=synth``'s ``data.source`` node (the split sizes are ``data.num_train``,
    ``num_val`` and ``num_test``)."""

    num_steps: int = 50  # frames per clip
    push_factor: float = 0.05  # the push's strength
    # the push's shape inside the radius: linear (DNRI's: fading in and out) or step (on and off at once: a positive
    # control for segment boundaries; simulate_push)
    push: str = "linear"
    seed: int = 1  # the data seed (the top-level seed drives the model and training); split i draws from seed*1000+i

    GENERATED: ClassVar[bool] = True  # data.num_* are the splits' sizes

    SETTINGS: ClassVar[dict[str, Rule]] = {
        "num_steps": integer(2), "push_factor": finite, "push": one_of(*PUSH_SHAPES),
        "seed": integer(-(2**53) + 1, " (magnitude < 2**53)", 2**53 - 1)}

    def clips(self, sizes: Mapping[str, int], cache_dir: Path) -> dict[str, Clips]:
        return read(self, sizes, cache_dir)

    def where(self) -> str:
        return "the push simulation"


def cache_params(s: Push, split: str, size: int) -> dict[str, Any]:
    """Everything that makes a split's clips: its cache key (the linear push's files predate the ``push`` key)."""
    shape = {} if s.push == "linear" else {"push": s.push}
    return {"kind": "push", "split": split, "num_samples": size, "num_steps": s.num_steps,
            "push_factor": s.push_factor, "seed": s.seed * 1000 + SPLITS.index(split), "version": 1, **shape}


def cache_path(s: Push, split: str, size: int, cache_dir: Path) -> Path:
    return cache_dir / f"synth_{split}_{cache_key(cache_params(s, split, size))}.pt"


def read(s: Push, sizes: Mapping[str, int], cache_dir: Path) -> dict[str, Clips]:
    """Each split of ``sizes`` (split -> number of clips), from the cache or simulated and cached."""

    def build(split: str, size: int, path: Path) -> dict[str, Any]:
        p = cache_params(s, split, size)
        log.info("generating %d synthetic %s clips -> %s", size, split, path)
        states, edges = simulate_push(size, s.num_steps, s.push_factor, seed=p["seed"], shape=s.push)
        return {"states": states, "edges": edges, "params": p}

    blobs = cached_splits(sizes, lambda split, size: cache_path(s, split, size, cache_dir), build)
    # edges[t] produced state t from t-1, so the transition t -> t+1 is labelled by edges[t+1].
    return {split: Clips(b["states"], edges=b["edges"][:, 1:]) for split, b in blobs.items()}
