"""An example track table to try the framework on before bringing your own: ``python -m dider.data.example
tracks.csv`` writes pedestrians crossing a plaza in the table format ``data=table`` reads (one row per agent and
frame: scene, agent, frame, x, y in metres, 10 frames a second).

Each scene holds a few walkers who enter at the plaza's edge at staggered times, walk towards the opposite edge at
1-1.6 m/s and leave there; a walker who comes within 2 m of another steps aside, away from them, for as long as
they are that close. These avoidance manoeuvres are the interactions a model can find.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from dider.io import atomic_write_bytes

FRAME_RATE = 10.0  # frames a second
RADIUS = 2.0  # m: closer than this, a walker steps aside
PUSH = 0.8  # m/s of sideways speed at contact, falling linearly to 0 at RADIUS
HALF_WIDTH = 6.0  # m: walkers enter at x = -6 or 6 and leave at the other edge


def example_tracks(scenes: int = 12, frames: int = 100, walkers: int = 6, seed: int = 0) -> pd.DataFrame:
    """The example table: ``scenes`` scenes of ``frames`` frames, each with ``walkers`` walkers (rows only while a
    walker is on the plaza). Columns scene, agent, frame, x, y."""
    rng = np.random.default_rng(seed)
    rows = []
    dt = 1.0 / FRAME_RATE
    for scene in range(scenes):
        side = rng.integers(0, 2, walkers) * 2 - 1  # -1: from the left edge, +1: from the right
        start = np.stack([-side * HALF_WIDTH, rng.uniform(-4, 4, walkers)], -1)
        speed = rng.uniform(1.0, 1.6, walkers)
        heading = np.stack([side * speed, rng.uniform(-0.2, 0.2, walkers)], -1)  # towards the other edge
        enter = rng.integers(0, frames // 3, walkers)
        pos = start.copy()
        for frame in range(frames):
            on = (frame >= enter) & (np.abs(pos[:, 0]) <= HALF_WIDTH)
            gap = pos[:, None] - pos[None]  # [W, W, 2]: from each other walker to this one
            dist = np.linalg.norm(gap, axis=-1) + np.eye(walkers) * 1e9
            near = on[:, None] & on[None] & (dist < RADIUS)
            strength = np.where(near, PUSH * (1 - dist / RADIUS), 0.0)
            away = (gap / dist[..., None] * strength[..., None]).sum(1)
            velocity = heading + away
            rows += [(scene, w, frame, pos[w, 0], pos[w, 1]) for w in np.flatnonzero(on)]
            pos = np.where((frame >= enter)[:, None], pos + velocity * dt, pos)
    table = pd.DataFrame(rows, columns=["scene", "agent", "frame", "x", "y"])
    return table.round({"x": 3, "y": 3})


def main(argv: Sequence[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(prog="python -m dider.data.example", description=__doc__.split("\n\n")[0])
    parser.add_argument("path", type=Path, help="the CSV file to write")
    parser.add_argument("--scenes", type=int, default=12, help="scenes (default 12)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    table = example_tracks(args.scenes, seed=args.seed)
    atomic_write_bytes(args.path, table.to_csv(index=False).encode())
    print(f"{args.path}: {len(table)} rows, {args.scenes} scenes, {table.groupby('scene').agent.nunique().sum()} "
          f"walkers, {FRAME_RATE:g} frames a second (python -m dider.run data=table data.source.path={args.path} "
          f"data.source.frame_rate={FRAME_RATE:g} ...)")
    return args.path


if __name__ == "__main__":
    main()
