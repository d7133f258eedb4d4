"""Small synthetic files in the exact formats of the real data sets (no real rows: those are licensed).

- inD / rounD / uniD: ``XX_tracks.csv``, ``XX_tracksMeta.csv``, ``XX_recordingMeta.csv`` with every real
  header column (dider.bench.fake_levelx writes them), parked vehicles, VRUs, tracks entering mid-recording.
- Basketball: Zhan et al.'s ``train.npz`` / ``test.npz`` (key ``data``, (S, 50, 22) feet) and DNRI's
  ``{loc,vel}_{train,valid,test}_bball.npy`` ([S, T, 5, 2]).
- Bring-your-own trajectories: an npz with ``positions`` and optional ``velocities``, ``mask``, ``edges``.
- Edges that come and go: a presence pattern [B, E, T] for the models' segment tests.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import torch

from dider.bench.fake_levelx import write_levelx_recording
from dider.graph import num_edges

# Location of each fake recording, mirroring inD's layout (00-06 location 4, 07-17 location 1, ...).
IND_LOCATIONS = {0: 4, 1: 4, 2: 1, 3: 1, 4: 2, 5: 3}


def write_ind_root(root: Path, num_recordings: int = 4, num_frames: int = 600, num_tracks: int = 6,
                   num_parked: int = 2, seed: int = 0) -> Path:
    """``num_recordings`` recordings 00, 01, ... of ``num_frames`` frames at 25 Hz in ``root``."""
    for r in range(num_recordings):
        write_levelx_recording(root, r, num_frames=num_frames, num_tracks=num_tracks, num_parked=num_parked,
                               seed=seed + r, location_id=IND_LOCATIONS.get(r, 1))
    return root


def write_background(root: Path, recording: str, rows: int = 90, cols: int = 120) -> Path:
    """A stand-in ``XX_background.png`` (a gradient; the real images are licensed)."""
    import matplotlib.image

    path = root / f"{recording}_background.png"
    matplotlib.image.imsave(path, np.linspace(0, 1, rows * cols).reshape(rows, cols), cmap="gray")
    return path


def edit_csv(path: Path, fn) -> None:
    """Rewrite a CSV through ``fn(DataFrame) -> DataFrame`` (to corrupt fixtures in tests)."""
    fn(pd.read_csv(path)).to_csv(path, index=False)


def bball_positions(rng: np.random.Generator, num: int, steps: int, agents: int) -> np.ndarray:
    """Random walks inside the 94 x 50 ft court: [num, steps, agents, 2] float64 (feet)."""
    start = rng.uniform([0.0, 0.0], [47.0, 50.0], (num, 1, agents, 2))
    walk = np.cumsum(rng.normal(0.0, 0.8, (num, steps, agents, 2)), axis=1)
    return np.clip(start + walk, [0.0, 0.0], [94.0, 50.0])


def write_zhan(root: Path, num_train: int = 40, num_test: int = 12, steps: int = 50, seed: int = 0,
               names: tuple[str, str] = ("train.npz", "test.npz")) -> dict[str, np.ndarray]:
    """Zhan et al. npz files: key 'data', (S, steps, 22) = ball + 5 offence + 5 defence (x, y)."""
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    out = {}
    for name, num in zip(names, (num_train, num_test), strict=True):
        data = bball_positions(rng, num, steps, 11).reshape(num, steps, 22)
        np.savez(root / name, data=data)
        out[name] = data
    return out


def write_dnri_bball(root: Path, sizes: dict[str, int] | None = None, steps: int = 49, agents: int = 5,
                     seed: int = 0) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """DNRI npy files: {loc,vel}_{split}_bball.npy, each [S, steps, agents, 2]."""
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    sizes = sizes or {"train": 30, "valid": 8, "test": 10}
    out = {}
    for split, num in sizes.items():
        loc = bball_positions(rng, num, steps + 1, agents)
        vel = np.diff(loc, axis=1)
        loc = loc[:, 1:]
        np.save(root / f"loc_{split}_bball.npy", loc)
        np.save(root / f"vel_{split}_bball.npy", vel)
        out[split] = (loc, vel)
    return out


def write_trajectories(path: Path, num: int = 40, steps: int = 20, agents: int = 3, velocities: bool = False,
                       mask: bool = False, edges: bool = False, seed: int = 0) -> dict[str, np.ndarray]:
    """A bring-your-own npz. With ``mask`` the last agent leaves after half the clip (NaN positions after);
    with ``edges`` a random int edge type per step and directed edge."""
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.normal(0, 0.1, (num, steps, agents, 2)), axis=1)
    arrays: dict[str, np.ndarray] = {"positions": walk}
    if velocities:
        arrays["velocities"] = rng.normal(0, 0.1, (num, steps, agents, 2))
    if mask:
        m = np.ones((num, steps, agents), bool)
        m[:, steps // 2:, -1] = False
        arrays["positions"][~m] = np.nan
        if velocities:
            arrays["velocities"][~m] = np.nan
        arrays["mask"] = m
    if edges:
        arrays["edges"] = rng.integers(0, 3, (num, steps, num_edges(agents)))
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arrays)
    return arrays


def comings_and_goings(b: int = 2, e: int = 6, t: int = 20, seed: int = 0) -> torch.Tensor:
    """[B, E, T] bool, an edge present at each step: each edge absent for a random stretch of 1-4 steps, at the
    clip's start, middle or end (so it enters part-way unless the stretch reaches the end)."""
    g = torch.Generator().manual_seed(seed)
    step = torch.arange(t)
    lo = torch.randint(0, t - 4, (b, e, 1), generator=g)
    hi = lo + torch.randint(1, 5, (b, e, 1), generator=g)
    return ~((step >= lo) & (step < hi))
