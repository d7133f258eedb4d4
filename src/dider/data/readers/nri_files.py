"""NRI's particle-system files (Kipf et al. 2018, ``data/generate_dataset.py``), the layout that NRI, fNRI, ACD,
NRI-MPM and other relational-inference codes read.

A folder holds, for each split (``train``, ``valid``, ``test``) and a suffix such as ``_springs5``:

- ``loc_{split}{suffix}.npy``: [S, T, 2, N] positions (x and y on axis 2, the balls on the last axis);
- ``vel_{split}{suffix}.npy``: [S, T, 2, N] velocities;
- ``edges_{split}{suffix}.npy``: [S, N, N] the clip's graph (NRI's static case), or [S, T, N, N] one per frame
  (this package's switching systems: ``edges[:, t]`` moved the balls from frame t-1 to frame t).

Labels are NRI's: ``floor((e + 1) / 2)``, which maps springs' {0, 1} and charges' products {-1, +1} to {0, 1}.
Edge direction follows NRI's code: ``edges[s, i, j]`` is the edge from ball j to ball i (its receivers are the
rows); NRI's own systems are symmetric, where this does not matter. Every problem raises naming the file.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch

from dider.data.clip_source import Clips
from dider.data.common import SPLITS, check_finite
from dider.data.readers.folder import data_root
from dider.data.sources import SourceSettings
from dider.graph import edge_index
from dider.io import atomic_write
from dider.validation import Rule

SPLIT_FILES = {"train": "train", "val": "valid", "test": "test"}  # our split -> NRI's name


@dataclass(frozen=True)
class NRIFiles(SourceSettings):
    """``data=nri_files``'s ``data.source`` node: ``{loc,vel,edges}_{train,valid,test}{suffix}.npy`` in ``root``."""

    root: str | None = None  # the folder of the files (required)
    suffix: str = "_springs5"  # NRI's file names: _springs5, _charged5, ...

    FIT_ON_FILE: ClassVar[bool] = True  # NRI fits the ranges on the whole training file, before any cap
    SETTINGS: ClassVar[dict[str, Rule]] = {"suffix": lambda v: None if isinstance(v, str) else "expected a string"}

    def clips(self, sizes: Mapping[str, int | None], cache_dir: Path) -> dict[str, Clips]:
        return read(self.root, self.suffix)

    def where(self) -> str:
        return f"data.source.root={self.root}"


def nri_path(root: Path, kind: str, split: str, suffix: str) -> Path:
    return root / f"{kind}_{SPLIT_FILES[split]}{suffix}.npy"


def _load(path: Path) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing (NRI's layout: loc_, vel_ and edges_ files for train, valid and "
                                f"test, named with data.source.suffix)")
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise ValueError(f"{path}: not a NumPy .npy array ({e})") from None
    if not (np.issubdtype(array.dtype, np.number) or array.dtype == bool) or np.iscomplexobj(array):
        raise ValueError(f"{path}: dtype {array.dtype}; expected real numbers")
    return array


def read_nri_split(root: Path, split: str, suffix: str) -> tuple[torch.Tensor, torch.Tensor]:
    """One split's files -> states [S, T, N, 4] float32 (x, y, vx, vy; raw units) and edges [S, T-1, E] long,
    the labels of the transitions t -> t+1 in this package's edge order (:mod:`dider.graph`)."""
    lpath, vpath, epath = (nri_path(root, k, split, suffix) for k in ("loc", "vel", "edges"))
    loc, vel, edges = _load(lpath), _load(vpath), _load(epath)
    if loc.ndim != 4 or loc.shape[2] != 2 or 0 in loc.shape:
        raise ValueError(f"{lpath}: shape {loc.shape}; expected [S, T, 2, N] (NRI's layout), non-empty")
    s, t, _, n = loc.shape
    if n < 2 or t < 2:
        raise ValueError(f"{lpath}: {n} ball(s) and {t} frame(s) per clip; need >= 2 of each")
    if vel.shape != loc.shape:
        raise ValueError(f"{vpath}: shape {vel.shape}; expected {loc.shape} as {lpath.name}")
    if edges.shape not in ((s, n, n), (s, t, n, n)):
        raise ValueError(f"{epath}: shape {edges.shape}; expected [S, N, N] = {(s, n, n)} or [S, T, N, N] = "
                         f"{(s, t, n, n)} to match {lpath.name} {loc.shape}")
    states = torch.from_numpy(np.concatenate([loc, vel], axis=2).astype(np.float32)).permute(0, 1, 3, 2)
    check_finite(f"{lpath} / {vpath.name}", states)
    e = torch.from_numpy(edges.astype(np.float64))
    check_finite(f"{epath}", e)
    labels = torch.floor((e + 1) / 2).long()
    if labels.min() < 0:
        raise ValueError(f"{epath}: values below -1 ({float(e.min())}) have no NRI label (floor((e + 1) / 2))")
    if labels.ndim == 3:
        labels = labels[:, None].expand(s, t, n, n)
    send, recv = edge_index(n)
    return states.contiguous(), labels[:, 1:, recv, send].contiguous()  # rows receive (NRI's code)


def read(root: str | Path | None, suffix: str) -> dict[str, Clips]:
    """Every split's files in the folder ``root`` (``data.source.root``) as clips, ids ``clip`` (the clip's index in its
    file)."""
    folder = data_root(root, "a folder of NRI's .npy files (or simulate them: data=springs, data=charged)")
    out = {}
    for split in SPLITS:
        states, edges = read_nri_split(folder, split, suffix)
        out[split] = Clips(states, edges=edges, ids={"clip": torch.arange(len(states))})
    return out


def write_nri_split(root: Path, split: str, suffix: str, loc: torch.Tensor, vel: torch.Tensor,
                    edges: torch.Tensor) -> None:
    """Write one split in NRI's layout (atomically): loc, vel [S, T, 2, N]; edges [S, N, N] or [S, T, N, N]."""
    root.mkdir(parents=True, exist_ok=True)
    for kind, array in (("loc", loc), ("vel", vel), ("edges", edges)):
        atomic_write(nri_path(root, kind, split, suffix), lambda f, a=array: np.save(f, a.numpy(), allow_pickle=False))
