"""Basketball player trajectories (Yue et al. 2014 STATS SportVU data, preprocessed by Zhan et al. or DNRI).

The data may not be redistributed: point ``data.root`` at a folder with either

- Zhan et al.'s ``train.npz`` / ``test.npz`` (or ``bball_train.npz`` / ``bball_test.npz``), key ``data``,
  shape (S, 50, 22): (x, y) in feet of the ball (columns 0-1), 5 offence players (2-11) and 5 defence
  players (12-21) at 6.25 Hz. DNRI's setting (the default): the 5 offence players, velocities by finite
  difference (so the first step is dropped: 49 steps), 40 burn-in steps + 9 predicted (horizons 1/5/9);
- or DNRI's ``{loc,vel}_{train,valid,test}_bball.npy``, each [S, T, N, 2] (used as they are).

The validation split is carved from the training file with a seeded permutation (``val_fraction``,
``seed``) when the files have none. Positions and velocities are normalised with the scalar min/max of
the training split (DNRI's scheme). All agents are present at every step (mask all True); no edges.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from dider.data.batch import Normalizer
from dider.data.common import ClipDataModule, ClipDataset, check_finite, spread_indices
from dider.data.loader import Loader
from dider.protocol import check_horizons
from dider.validation import Rule, above, check_settings, integer, one_of, optional, within_open

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
                         f"data.format=zhan or data.format=dnri")
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


def carve(num: int, fraction: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Reproducible (keep, carved) index split of range(num): ``round(fraction * num)`` (>= 1) carved."""
    take = max(1, round(fraction * num))
    if take >= num:
        raise ValueError(f"data.val_fraction={fraction}: carving {take} of {num} training clips leaves none")
    perm = torch.randperm(num, generator=torch.Generator().manual_seed(seed))
    return perm[take:].sort().values, perm[:take].sort().values


class BasketballDataModule(ClipDataModule):
    """Basketball clips: states [B, T, N, 4] normalised, mask [B, T, N] all True (see the module docstring).

    After ``setup``: ``normalizer``, ``datasets`` (ClipDataset per split), ``format`` ('zhan' or 'dnri').
    ``cache_dir`` is accepted for a uniform interface; loading the arrays is fast, so nothing is cached.
    """

    units = "ft"

    SETTINGS: ClassVar[dict[str, Rule | type]] = ClipDataModule.SETTINGS | {
        "format": one_of("auto", "zhan", "dnri"), "agents": one_of(*AGENT_COLUMNS), "val_fraction": within_open(0, 1),
        "frame_rate": above(0), "train_len": optional(integer(2)),
    }
    LOADER = Loader(batch_size=128, eval_batch_size=128)  # DNRI's basketball batch

    def __init__(
        self,
        root: str | None = None,
        format: str = "auto",
        agents: str = "offence",
        frame_rate: float = 6.25,
        val_fraction: float = 0.1,
        seed: int = 1,
        train_len: int | None = None,
        burn_in: int = 40,
        horizons: Sequence[int] = (1, 5, 9),
        num_train: int | None = None,
        num_val: int | None = None,
        num_test: int | None = None,
        loader: Mapping[str, Any] | None = None,
        cache_dir: str | None = None,
        burn_in_mode: str = "global",
    ) -> None:
        """format: auto (from the files in ``root``) | zhan | dnri.
        agents: the Zhan files' agents: offence (DNRI's) | defence | players (all 10) | all (the ball and the 10).
        frame_rate: the Zhan files' rate in Hz; finite-difference velocities are in feet / second.
        val_fraction: the training clips carved off for validation when the files have no validation split.
        seed: the carving seed.
        train_len: crop training clips to their first steps (DNRI trains on 40); null: whole clips."""
        super().__init__()
        check_settings(self, locals(), key="data")
        self.save_hyperparameters(logger=False)
        self.init_shared()  # the clip length is known once the files are read: horizons checked in setup
        self.format: str | None = None

    def _root(self) -> Path:
        if self.hparams.root is None:
            raise ValueError("data.root is not set: point it at the folder with train.npz/test.npz (Zhan et "
                             "al.) or {loc,vel}_{train,valid,test}_bball.npy (DNRI)")
        root = Path(self.hparams.root).expanduser()
        if not root.is_dir():
            raise FileNotFoundError(f"data.root={root}: no such folder")
        return root

    def load_raw(self) -> dict[str, torch.Tensor]:
        """Raw states per split, [S, T, N, 4] in feet (and feet / s or the file's velocity units)."""
        h = self.hparams
        root = self._root()
        fmt = detect_format(root) if h.format == "auto" else h.format
        self.format = fmt
        if fmt == "zhan":
            pair = next((p for p in ZHAN_FILES if all((root / f).is_file() for f in p)), ZHAN_FILES[0])
            train = load_zhan(root / pair[0], h.agents, h.frame_rate)
            raw = {"test": load_zhan(root / pair[1], h.agents, h.frame_rate)}
            has_val = False
        else:
            if h.agents != "offence":
                log.warning("data.agents=%s ignored: DNRI's npy files hold their own agents", h.agents)
            train, raw = load_dnri(root, "train"), {"test": load_dnri(root, "test")}
            has_val = _dnri_path(root, "loc", "val").is_file()
            if has_val:
                raw["val"] = load_dnri(root, "val")
        if not has_val:  # carve validation clips from train, reproducibly
            keep, val = carve(train.shape[0], h.val_fraction, h.seed)
            train, raw["val"] = train[keep], train[val]
        raw["train"] = train
        for split, x in raw.items():
            if x.shape[2:] != train.shape[2:]:  # clip lengths may differ between files, agents may not
                raise ValueError(f"basketball {split} clips have {x.shape[2]} agents, train {train.shape[2]}")
            if x.shape[0] == 0:
                raise ValueError(f"basketball {split} split has no clips ({root})")
        return {s: raw[s] for s in ("train", "val", "test")}

    def setup(self, stage: str | None = None) -> None:
        if self.datasets:
            return
        h = self.hparams
        raw = self.load_raw()
        # Forecasting needs the full clip at val/test; DNRI trains on shorter crops (train_len 40).
        check_horizons(h.horizons, raw["test"].shape[1], h.burn_in, where=f" in {h.root}")
        check_horizons(h.horizons, raw["val"].shape[1], h.burn_in, where=f" in {h.root}, validation")
        if h.train_len is not None:
            if h.train_len > raw["train"].shape[1]:
                raise ValueError(f"data.train_len={h.train_len}: longer than the training clips "
                                 f"({raw['train'].shape[1]} steps)")
            raw["train"] = raw["train"][:, : h.train_len]
        caps = {"train": h.num_train, "val": h.num_val, "test": h.num_test}
        raw = {s: x[spread_indices(x.shape[0], caps[s])] for s, x in raw.items()}
        try:
            self.normalizer = self.train_normalizer(lambda: Normalizer.fit(raw["train"]))
        except ValueError as err:  # e.g. constant positions: nothing to scale by
            raise ValueError(f"basketball training clips in data.root={self.hparams.root}: {err}") from err
        for split, x in raw.items():
            mask = torch.ones(x.shape[:3], dtype=torch.bool)
            self.datasets[split] = ClipDataset(self.normalizer.normalize(x).contiguous(), mask)
        log.info("basketball (%s): %s clips of %s steps, %d agents", self.format,
                 {s: len(d) for s, d in self.datasets.items()}, raw["test"].shape[1], raw["test"].shape[2])
