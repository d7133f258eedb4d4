"""ETH/UCY pedestrians as the trajectory-forecasting literature ships them (Social GAN's copies): plain text, one row
per pedestrian per frame, ``frame agent x y`` separated by tabs or spaces, no header, positions in metres, frames
numbered in the original video (a step every 10 frames, or 6 in ETH's own file). A folder reads each ``.txt`` file
in it as one scene named by the file; a file alone is one scene. Frames become steps: each file's frame numbers
divided by their common step, so that every scene is at the data set's 2.5 steps a second (``data=eth_ucy``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from dider.data.track_sources import TrackFile

FIELDS = ("frame", "agent", "x", "y")


@dataclass(frozen=True)
class EthUcyFiles(TrackFile):
    """``data=eth_ucy``'s ``data.source`` node: ``path``, a folder of the text files or one of them."""

    frame_rate: float = 2.5  # the data set's steps a second, once frames are steps

    def read(self, path: Path) -> pd.DataFrame:
        files = sorted(path.glob("*.txt")) if path.is_dir() else [path]
        if not files:
            raise FileNotFoundError(f"data.source.path={path}: no .txt files in the folder")
        return pd.concat([_scene(f) for f in files], ignore_index=True)


def _scene(file: Path) -> pd.DataFrame:
    rows, lines = [], []
    for n, line in enumerate(file.read_text().splitlines(), 1):
        if not (fields := line.split()):
            continue
        try:
            values = [float(v) for v in fields]
        except ValueError:
            values = []
        if len(values) != len(FIELDS) or not all(map(math.isfinite, values)):
            raise ValueError(f"{file}: line {n} is not four numbers (frame agent x y): {line.strip()!r}")
        rows.append(values)
        lines.append(n)
    if not rows:
        raise ValueError(f"{file}: no rows (expected lines of frame agent x y)")
    table = np.array(rows)
    for col, name in ((0, "frame"), (1, "agent")):  # numbers of frames and pedestrians: truncating would merge them
        if (bad := np.flatnonzero(table[:, col] != np.round(table[:, col]))).size:
            n = lines[bad[0]]
            raise ValueError(f"{file}: line {n}: the {name} number {float(table[bad[0], col]):g} is not a whole number "
                             f"({bad.size} such line(s))")
    frame = table[:, 0].astype(np.int64)
    step = int(np.gcd.reduce(np.diff(np.unique(frame)))) or 1
    return pd.DataFrame({"scene": file.stem, "agent": table[:, 1].astype(np.int64), "frame": frame // step,
                         "x": table[:, 2], "y": table[:, 3]})
