"""NRI's particle systems (Kipf et al. 2018), the relational-inference field's shared benchmark, vectorised over clips,
and their clip source (``data=springs``, ``data=charged``).

N balls move in a 2-D box of half-width 5 with elastic walls, integrated with a step of 1e-3 and recorded every
``sample_every`` steps (NRI's 100), each force component clipped to 100:

- ``springs``: each pair of balls is joined by a spring (stiffness 0.1) with probability 1/2, so ball i feels
  -0.1 * sum_j e_ij (x_i - x_j); the initial positions have standard deviation 0.5. Edge label e_ij in {0, 1}.
- ``charged``: each ball carries a charge of +1 or -1 (probability 1/2 each), so ball i feels
  sum_j q_i q_j (x_i - x_j) / |x_i - x_j|^3 (like charges repel); initial positions with standard deviation 1.
  Edge label (q_i q_j + 1) / 2: 0 attract, 1 repel (NRI's labels).

Velocities start with norm 0.5 in a random direction. NRI's graph is static. ``switch_prob`` > 0 makes it switch
within a clip, the case segment models exist for: before each recorded frame after the first, each spring breaks
or forms (springs) or each ball's charge flips (charged) with that probability, so the labels are per step.

Alignment: ``edges[:, t]`` is the graph that moved the balls from frame t-1 to frame t (for t = 0, from the start
of the simulation), the convention of :mod:`dider.data.simulators.push`; frame 0 is the state after
``sample_every`` integration steps, as in NRI's generator, which records from there.

The source (:class:`Simulation`) simulates each split from its own seed, cached under the cache folder by every
setting that made it. Its clips' edges come receiver-major as in NRI's files, one per transition t -> t+1; ids:
``clip``, the clip's index.
"""

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
from dider.data.sources import SourceSettings
from dider.graph import edge_index
from dider.validation import Rule, integer, one_of, within

log = logging.getLogger(__name__)

SYSTEMS = ("springs", "charged")
BOX = 5.0
DT = 1e-3
MAX_FORCE = 0.1 / DT
STIFFNESS = 0.1  # springs
COULOMB = 1.0  # charged
LOC_STD = {"springs": 0.5, "charged": 1.0}
SPEED = 0.5


def _forces(system: str, x: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
    """x [S, N, 2], e [S, N, N] pair weights (zero diagonal) -> forces [S, N, 2], each component clipped."""
    if system == "springs":  # -k sum_j e_ij (x_i - x_j), as a matrix product (no [S, N, N, 2] tensor)
        f = -STIFFNESS * (e.sum(-1, keepdim=True) * x - e @ x)
    else:
        r = x[:, :, None] - x[:, None]  # [S, N, N, 2]: x_i - x_j
        dist3 = r.square().sum(-1).pow(1.5)  # [S, N, N]; 0 on the diagonal, where e is 0 too
        weight = torch.where(e != 0, COULOMB * e / dist3.clamp_min(1e-300), 0.0)
        f = (weight[..., None] * r).sum(2)
    return f.clamp(-MAX_FORCE, MAX_FORCE)


def _bounce(x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Reflect positions beyond the walls back inside and turn their velocity component inwards."""
    over, under = x > BOX, x < -BOX
    x = torch.where(over, 2 * BOX - x, torch.where(under, -2 * BOX - x, x))
    v = torch.where(over, -v.abs(), torch.where(under, v.abs(), v))
    return x, v


def _graph_path(system: str, num_samples: int, num_frames: int, n: int, switch_prob: float,
                g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """The graph of every frame interval: pair weights [S, T, N, N] float64 and labels [S, T, N, N] long."""
    if system == "springs":
        upper = torch.triu(torch.ones(n, n, dtype=torch.bool), diagonal=1)
        state = torch.rand(num_samples, 1, n, n, generator=g) < 0.5
        flips = torch.rand(num_samples, num_frames, n, n, generator=g) < switch_prob
        flips[:, 0] = False
        state = (state ^ (flips.long().cumsum(1) % 2).bool()) & upper  # one draw per pair, mirrored below
        label = (state | state.transpose(-1, -2)).long()
        return label.double(), label
    charge = torch.rand(num_samples, 1, n, generator=g) < 0.5
    flips = torch.rand(num_samples, num_frames, n, generator=g) < switch_prob
    flips[:, 0] = False
    q = (charge ^ (flips.long().cumsum(1) % 2).bool()).double() * 2 - 1  # [S, T, N] in {-1, +1}
    weight = q[..., :, None] * q[..., None, :] * (1 - torch.eye(n, dtype=torch.float64))
    return weight, ((weight + 1) / 2).floor().long() * (1 - torch.eye(n, dtype=torch.long))


def simulate_particles(system: str, num_samples: int, num_frames: int = 49, num_balls: int = 5,
                       sample_every: int = 100, switch_prob: float = 0.0, seed: int = 0,
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Simulate ``num_samples`` clips of an NRI system (module docstring).

    Returns, in NRI's file layout: loc [S, T, 2, N] and vel [S, T, 2, N] float64, and edges [S, T, N, N] long,
    the symmetric label matrix of each frame's interval (constant over T when switch_prob is 0).
    """
    if system not in SYSTEMS:
        raise ValueError(f"simulate_particles: system={system!r}: expected one of {list(SYSTEMS)}")
    for name, value, low in (("num_samples", num_samples, 1), ("num_frames", num_frames, 2),
                             ("num_balls", num_balls, 2), ("sample_every", sample_every, 1)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"simulate_particles: {name}={value!r}: need an integer >= {low}")
    if isinstance(switch_prob, bool) or not isinstance(switch_prob, (int, float)) or not 0 <= switch_prob <= 1:
        raise ValueError(f"simulate_particles: switch_prob={switch_prob!r}: need a number in [0, 1]")
    g = torch.Generator().manual_seed(int(seed))
    n = num_balls
    weight, labels = _graph_path(system, num_samples, num_frames, n, float(switch_prob), g)
    x = torch.randn(num_samples, n, 2, generator=g, dtype=torch.float64) * LOC_STD[system]
    v = torch.randn(num_samples, n, 2, generator=g, dtype=torch.float64)
    v = v * SPEED / v.norm(dim=-1, keepdim=True)
    x, v = _bounce(x, v)
    loc = torch.empty(num_samples, num_frames, n, 2, dtype=torch.float64)
    vel = torch.empty_like(loc)
    # Frame k is recorded after step (k + 1) * sample_every; the forces of steps k * sample_every up to the one
    # before it move the balls there, under the graph of interval k.
    v = v + DT * _forces(system, x, weight[:, 0])
    for step in range(1, (num_frames + 1) * sample_every):
        x, v = _bounce(x + DT * v, v)
        if step % sample_every == 0:
            k = step // sample_every - 1
            loc[:, k], vel[:, k] = x, v
            if k == num_frames - 1:
                break
        v = v + DT * _forces(system, x, weight[:, min(step // sample_every, num_frames - 1)])
    if not (torch.isfinite(loc).all() and torch.isfinite(vel).all()):
        raise ValueError(f"simulate_particles: {system} produced non-finite states")
    return loc.transpose(2, 3).contiguous(), vel.transpose(2, 3).contiguous(), labels


@dataclass(frozen=True)
class Simulation(SourceSettings):
    """What ``data=springs`` / ``data=charged`` simulate (:func:`simulate_particles`): their ``data.source`` node; the
    split sizes are ``data.num_train``, ``num_val`` and ``num_test``."""

    system: str = "springs"  # springs or charged (data=nri_files reads NRI's files: dider.data.readers.nri_files)
    num_balls: int = 5
    num_frames: int = 49  # frames per clip (NRI: 49 for training, 99 in its test files)
    sample_every: int = 100  # integration steps per frame
    switch_prob: float = 0.0  # chance per frame that a spring breaks or forms / a charge flips (0: NRI's static graph)
    seed: int = 1  # the data seed; each split draws from its own stream

    GENERATED: ClassVar[bool] = True  # data.num_* are the splits' sizes

    SETTINGS: ClassVar[dict[str, Rule]] = {
        "system": one_of(*SYSTEMS), "num_balls": integer(2), "num_frames": integer(2),
        "sample_every": integer(1), "switch_prob": within(0.0, 1.0), "seed": integer(0, "", 2**31 - 1)}

    def clips(self, sizes: Mapping[str, int], cache_dir: Path) -> dict[str, Clips]:
        return read(self, sizes, cache_dir)

    def where(self) -> str:
        return f"the {self.system} simulation"


def cache_path(sim: Simulation, split: str, size: int, cache_dir: Path) -> Path:
    params = {**asdict(sim), "split": split, "num_samples": size, "version": 1}  # every setting
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
