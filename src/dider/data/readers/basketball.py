"""Basketball player trajectories (Yue et al. 2014 STATS SportVU data, preprocessed by Zhan et al. or DNRI) as a clip
source (``data=basketball``). The data may not be redistributed; ``data.source.root`` is a folder with either

- Zhan et al.'s ``train.npz`` / ``test.npz`` (or ``bball_train.npz`` / ``bball_test.npz``), key ``data``,
  shape (S, 50, 22): (x, y) in feet of the ball (columns 0-1), 5 offence players (2-11) and 5 defence
  players (12-21) at 6.25 Hz; velocities by finite difference (so the first step is dropped: 49 steps);
- or DNRI's ``{loc,vel}_{train,valid,test}_bball.npy``, each [S, T, N, 2] (used as they are).

Every agent is present at every step; no edges, no ids.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch

from dider.data.clip_source import Clips
from dider.data.common import check_finite
from dider.data.readers.folder import data_root
from dider.data.sources import SourceSettings
from dider.validation import Rule, above, one_of

log = logging.getLogger(__name__)

ZHAN_FILES = [("train.npz", "test.npz"), ("bball_train.npz", "bball_test.npz")]
DNRI_SPLITS = {"train": "train", "val": "valid", "test": "test"}
# Column ranges of the (S, T, 22) Zhan layout: ball, offence, defence as (x, y) pairs.
AGENT_COLUMNS = {"offence": (2, 12), "defence": (12, 22), "players": (2, 22), "all": (0, 22)}


def _dnri_path(root: Path, kind: str, split: str) -> Path:
    return root / f"{kind}_{DNRI_SPLITS[split]}_bball.npy"


def detect_format(root: Path) -> str:
    """'zhan' or 'dnri' from the files present in ``root``."""
    zhan = any(all((root / f).is_file() for f in pair) for pair in ZHAN_FILES)
    dnri = all(_dnri_path(root, k, s).is_file() for k in ("loc", "vel") for s in ("train", "test"))
    if zhan and dnri:
        raise ValueError(f"{root}: holds both Zhan npz and DNRI npy basketball files; set "
                         f"data.source.format=zhan or data.source.format=dnri")
    if not (zhan or dnri):
        raise FileNotFoundError(
            f"{root}: no basketball data found: expected train.npz + test.npz (Zhan et al., key 'data') or "
            f"{{loc,vel}}_{{train,valid,test}}_bball.npy (DNRI)")
    return "zhan" if zhan else "dnri"


def _read(path: Path, key: str | None = None) -> np.ndarray:
    """One numeric array from an npz (``key``) or a npy file (``key=None``). Unreadable, pickled or
    non-numeric content raises a ValueError naming the file and key, never an error from inside numpy."""
    what = f"{path}" + (f" key {key!r}" if key else "")
    try:
        loaded = np.load(path, allow_pickle=False)
        files = None
        if isinstance(loaded, np.lib.npyio.NpzFile):
            with loaded:
                files = loaded.files
                arr = loaded[key] if key in files else None
        else:
            arr = None if key is not None else loaded
    except Exception as err:  # corrupt archives raise zipfile, OSError, EOFError, NotImplementedError, ...
        raise ValueError(f"{what}: unreadable ({type(err).__name__}: {err})") from err
    if arr is None:
        if key is None:
            raise ValueError(f"{path}: an .npz archive (keys {files}); expected a .npy array")
        held = f"keys: {files}" if files is not None else "a single .npy array"
        raise ValueError(f"{path}: no key {key!r} ({held}); expected Zhan et al.'s (S, 50, 22) array")
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool) or np.iscomplexobj(arr):
        raise ValueError(f"{what}: dtype {arr.dtype} is not real-valued numeric")
    return arr


def load_zhan(path: Path, agents: str, frame_rate: float) -> torch.Tensor:
    """One Zhan npz -> states [S, T-1, N, 4] float32 (x, y, vx, vy): positions in feet from step 1 on,
    velocities (pos[t] - pos[t-1]) * frame_rate (feet / second when frame_rate is the 6.25 Hz rate)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing")
    arr = _read(path, "data")
    if arr.ndim != 3 or arr.shape[2] != 22 or arr.shape[1] < 2:
        raise ValueError(f"{path}: key 'data' has shape {arr.shape}; expected (S, T, 22) = ball + 5 offence "
                         f"+ 5 defence (x, y) per step, T >= 2")
    lo, hi = AGENT_COLUMNS[agents]
    pos = torch.from_numpy(np.ascontiguousarray(arr[:, :, lo:hi], dtype=np.float32))
    pos = pos.reshape(arr.shape[0], arr.shape[1], (hi - lo) // 2, 2)
    check_finite(f"{path}: key 'data'", pos)
    vel = (pos[:, 1:] - pos[:, :-1]) * frame_rate
    return torch.cat([pos[:, 1:], vel], dim=-1)


def load_dnri(root: Path, split: str) -> torch.Tensor:
    """DNRI's loc/vel npy pair of a split -> states [S, T, N, 4] float32."""
    parts = []
    for kind in ("loc", "vel"):
        path = _dnri_path(root, kind, split)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: missing (DNRI basketball format needs loc_* and vel_* files)")
        arr = _read(path)
        if arr.ndim != 4 or arr.shape[-1] != 2:
            raise ValueError(f"{path}: shape {arr.shape}; expected [S, T, N, 2]")
        parts.append(torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float32)))
        check_finite(str(path), parts[-1])
    if parts[0].shape != parts[1].shape:
        raise ValueError(f"{_dnri_path(root, 'vel', split)}: shape {tuple(parts[1].shape)} differs from "
                         f"{_dnri_path(root, 'loc', split).name} {tuple(parts[0].shape)}")
    return torch.cat(parts, dim=-1)


@dataclass(frozen=True)
class BasketballFiles(SourceSettings):
    """``data=basketball``'s ``data.source`` node."""

    root: str | None = None  # the folder of the files (required)
    format: str = "auto"  # auto (from the files in root) | zhan | dnri
    agents: str = "offence"  # the Zhan files' agents: offence (DNRI's) | defence | players (all 10) | all (+ ball)
    frame_rate: float = 6.25  # the Zhan files' rate in Hz: finite-difference velocities are in feet / second

    UNITS: ClassVar[str] = "ft"
    SPLIT_SETTINGS: ClassVar[tuple[str, ...]] = ("val_fraction", "seed")  # Zhan's files have no validation split
    SETTINGS: ClassVar[dict[str, Rule]] = {"format": one_of("auto", "zhan", "dnri"),
                                           "agents": one_of(*AGENT_COLUMNS), "frame_rate": above(0)}

    def clips(self, sizes: Mapping[str, int | None], cache_dir: Path) -> dict[str, Clips]:
        """Train and test, and val where the files have one (else the data module carves it from train)."""
        fmt, parts = read(self.root, self.format, self.agents, self.frame_rate)
        log.info("basketball files in %s: %s format", self.root, fmt)
        return parts

    def where(self) -> str:
        return f"data.source.root={self.root}"


def read(root: str | Path | None, format: str = "auto", agents: str = "offence",
         frame_rate: float = 6.25) -> tuple[str, dict[str, Clips]]:
    """(the format read, 'zhan' or 'dnri'; its splits: train and test, and val where the files have one)."""
    folder = data_root(root, "the folder with train.npz/test.npz (Zhan et al.) or "
                             "{loc,vel}_{train,valid,test}_bball.npy (DNRI)")
    fmt = detect_format(folder) if format == "auto" else format
    if fmt == "zhan":
        pair = next((p for p in ZHAN_FILES if all((folder / f).is_file() for f in p)), ZHAN_FILES[0])
        raw = {s: load_zhan(folder / name, agents, frame_rate) for s, name in zip(("train", "test"), pair, strict=True)}
    else:
        if agents != "offence":
            log.warning("data.source.agents=%s ignored: DNRI's npy files hold their own agents", agents)
        has_val = _dnri_path(folder, "loc", "val").is_file()
        raw = {s: load_dnri(folder, s) for s in ("train", "test", "val")[:3 if has_val else 2]}
    return fmt, {s: Clips(x) for s, x in raw.items()}
