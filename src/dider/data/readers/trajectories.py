"""The ``.npz`` trajectory layout (``data=trajectories``): one file of fixed-length multi-agent clips.

Keys (others are ignored):
- ``positions``  [S, T, N, 2] float, required;
- ``velocities`` [S, T, N, 2] float, optional: else finite differences (pos[t] - pos[t-1]) * frame_rate,
  which drops the first step (T-1 steps remain) and needs the agent at both steps;
- ``mask``       [S, T, N] bool (or 0/1), optional: agent present; values of absent agents may be NaN;
- ``edges``      [S, T, N(N-1)] int >= 0, optional ground-truth edge types in the synthetic data's
  convention: edges[:, t] is the interaction that produced step t from step t-1, edge order of
  dider.graph (sender-major, no self edges). Batches then carry ``edges`` [B, T'-1, E] for the
  transitions t -> t+1 of the clip (edges[:, 1:], or edges[:, 2:] when velocities are differenced).
"""

from __future__ import annotations

import zipfile
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from dider.data.clip_source import Clips
from dider.data.common import check_finite
from dider.data.sources import SourceSettings
from dider.data.windowing import midpoint
from dider.graph import num_edges
from dider.protocol import fill_absent
from dider.validation import Rule, above

# What a damaged or foreign file can raise while numpy opens or decompresses it.
_READ_ERRORS = (ValueError, OSError, EOFError, KeyError, NotImplementedError, zipfile.BadZipFile, zlib.error)


@dataclass(frozen=True)
class NpzFile(SourceSettings):
    """``data=trajectories``'s ``data.source`` node."""

    path: str | None = None  # the .npz file (required)
    frame_rate: float = 1.0  # finite-difference velocities = (pos[t] - pos[t-1]) * frame_rate (no 'velocities')

    SPLIT_SETTINGS: ClassVar[tuple[str, ...]] = ("split", "seed")  # the module splits the file's clips
    SETTINGS: ClassVar[dict[str, Rule]] = {"frame_rate": above(0)}

    def clips(self, sizes: Mapping[str, int | None], cache_dir: Path) -> dict[str, Clips]:
        """Every clip of the file as one part (``all``): the data module splits them."""
        return {"all": read(self.path, self.frame_rate)}

    def predict_clips(self) -> Clips:
        return read(self.path, self.frame_rate)

    def where(self) -> str:
        return f"data.source.path={self.path}"


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    """The known keys of the archive (numeric arrays only, no pickles); errors name the file and key."""
    try:
        z = np.load(path, allow_pickle=False)
    except _READ_ERRORS as e:
        raise ValueError(f"{path}: not a readable .npz file ({type(e).__name__}: {e})") from e
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise ValueError(f"{path}: a single .npy array, not an .npz archive with key 'positions' [S, T, N, 2]")
    arrays = {}
    with z:
        if "positions" not in z.files:
            raise ValueError(f"{path}: no key 'positions' (keys: {z.files}); expected [S, T, N, 2]")
        for key in ("positions", "velocities", "mask", "edges"):
            if key not in z.files:
                continue
            try:
                arrays[key] = z[key]
            except _READ_ERRORS as e:
                raise ValueError(f"{path}: key {key!r} cannot be read ({type(e).__name__}: {e})") from e
    return arrays


def _float32(a: np.ndarray) -> torch.Tensor:
    """float32 copy; values beyond its range become inf, which check_finite then reports by key."""
    with np.errstate(over="ignore", invalid="ignore"):
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))


def load_trajectories(path: Path, frame_rate: float = 1.0) -> dict[str, Any]:
    """Read and validate the file -> states [S, T', N, 4] float32 (raw, zeros where absent), mask
    [S, T', N] bool and, if present, edges [S, T'-1, E] long (the transitions of the clip).

    Every problem raises ValueError (FileNotFoundError for a missing file) naming the file and the key.
    """
    if not path.is_file():
        raise FileNotFoundError(f"data.source.path={path}: no such file")
    arrays = _read_npz(path)
    return trajectory_states(arrays, path, frame_rate, _centre(arrays))


def _centre(arrays: dict[str, np.ndarray]) -> tuple[float, float]:
    """The centre of the file's finite present positions (float64): the origin its clips are relative to (a file
    that is not of the layout: 0, and :func:`trajectory_states` names what is wrong)."""
    pos, mask = arrays["positions"], arrays.get("mask")
    if pos.dtype.kind not in "iuf" or pos.ndim != 4 or pos.shape[-1] != 2:
        return (0.0, 0.0)
    flat = pos.reshape(-1, 2).astype(np.float64)
    keep = np.isfinite(flat).all(1)
    if mask is not None and mask.shape == pos.shape[:3]:
        keep &= mask.reshape(-1).astype(bool)
    return midpoint(flat[keep])


def trajectory_states(arrays: dict[str, np.ndarray], path: str | Path, frame_rate: float = 1.0,
                      origin: tuple[float, float] = (0.0, 0.0)) -> dict[str, Any]:
    """Validate arrays of the npz layout (module docstring; ``path`` names their origin in errors) -> states
    [S, T', N, 4] float32 raw (positions less ``origin``, subtracted in float64 before the cast; zeros where
    absent), mask [S, T', N] bool, edges [S, T'-1, E] long if given, and ``first_frame``: the input's time index
    of step 0."""
    if "positions" not in arrays:
        raise ValueError(f"{path}: no 'positions' [S, T, N, 2]")
    for key, a in arrays.items():
        kinds = "biuf" if key in ("mask", "edges") else "iuf"
        if a.dtype.kind not in kinds:
            raise ValueError(f"{path}: key {key!r} has dtype {a.dtype}; expected real numbers")
    pos = arrays["positions"]
    if pos.ndim != 4 or pos.shape[-1] != 2 or min(pos.shape) == 0:
        raise ValueError(f"{path}: key 'positions' has shape {pos.shape}; expected [S, T, N, 2] (non-empty)")
    s, t, n, _ = pos.shape
    if n < 2:
        raise ValueError(f"{path}: key 'positions' has {n} agent(s) per clip; relations need >= 2")
    if origin != (0.0, 0.0):
        with np.errstate(over="ignore", invalid="ignore"):  # inf stays inf, for check_finite to name
            pos = pos.astype(np.float64) - np.asarray(origin)
    pos, mask = _float32(pos), _mask(arrays, path, (s, t, n))
    hint = "" if "mask" in arrays else " (mark absent agents with a 'mask' key)"
    check_finite(f"{path}: key 'positions'{hint}", pos, mask[..., None])
    pos, vel, mask, drop = _velocities(arrays, path, pos, mask, frame_rate, hint)
    # first_frame: the file's time index of the clip's step 0 (1 when the first step went to differencing)
    out = {"states": fill_absent(torch.cat([pos, vel], dim=-1), mask), "mask": mask, "first_frame": drop,
           "origin": origin}
    if "edges" in arrays:
        # edges[t] produced step t from t-1, so the clip's transition j -> j+1 (raw step drop+j -> drop+j+1)
        # is labelled by raw edges[drop + j + 1].
        out["edges"] = _edges(arrays["edges"], path, (s, t, num_edges(n)))[:, drop + 1:]
    return out


def _mask(arrays: dict[str, np.ndarray], path: str | Path, shape: tuple[int, int, int]) -> torch.Tensor:
    """The ``mask`` key as [S, T, N] bool (every agent present without one)."""
    if "mask" not in arrays:
        return torch.ones(shape, dtype=torch.bool)
    m = arrays["mask"]
    if m.shape != shape:
        raise ValueError(f"{path}: key 'mask' has shape {m.shape}; expected [S, T, N] = {shape}")
    if m.dtype != bool and not np.isin(m, (0, 1)).all():
        raise ValueError(f"{path}: key 'mask' must be bool or 0/1 (dtype {m.dtype})")
    return torch.from_numpy(m.astype(bool))


def _velocities(arrays: dict[str, np.ndarray], path: str | Path, pos: torch.Tensor, mask: torch.Tensor,
                frame_rate: float, hint: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int]:
    """(positions, velocities, mask, steps dropped): the ``velocities`` key, or finite differences of the
    positions x frame_rate, which drop the first step. pos: [S, T, N, 2], mask: [S, T, N]."""
    if "velocities" in arrays:
        v = arrays["velocities"]
        if v.shape != pos.shape:
            raise ValueError(f"{path}: key 'velocities' has shape {v.shape}; expected {tuple(pos.shape)} like "
                             f"positions")
        vel = _float32(v)
        check_finite(f"{path}: key 'velocities'{hint}", vel, mask[..., None])
        return pos, vel, mask, 0
    if pos.shape[1] < 2:
        raise ValueError(f"{path}: key 'positions' has {pos.shape[1]} step(s): finite-difference velocities need "
                         f">= 2")
    # A velocity needs the agent at both ends of the step.
    vel = (pos[:, 1:] - pos[:, :-1]) * frame_rate
    pos, mask = pos[:, 1:], mask[:, 1:] & mask[:, :-1]
    check_finite(f"{path}: key 'positions' (finite-difference velocities x data.source.frame_rate={frame_rate})",
                 vel, mask[..., None])
    return pos, vel, mask, 1


def _edges(e: np.ndarray, path: str | Path, shape: tuple[int, int, int]) -> torch.Tensor:
    """The ``edges`` key as [S, T, E] long, checked to hold non-negative integer edge types."""
    if e.shape != shape:
        raise ValueError(f"{path}: key 'edges' has shape {e.shape}; expected [S, T, N(N-1)] = {shape}")
    if e.dtype.kind == "f" and not (np.isfinite(e).all() and (e == np.round(e)).all()):
        raise ValueError(f"{path}: key 'edges' must hold integer edge types (dtype {e.dtype})")
    if (e < 0).any():
        raise ValueError(f"{path}: key 'edges' has negative edge types")
    if e.size and e.max() >= 2**31:
        raise ValueError(f"{path}: key 'edges' has edge type {e.max()}: implausibly large")
    return torch.from_numpy(e.astype(np.int64))


def read(path: str | Path | None, frame_rate: float = 1.0) -> Clips:
    """The clips of the file ``path`` (``data.source.path``), ids ``clip`` (the clip's index in the file) and ``frame``
    (the file's time index of the clip's step 0)."""
    if path is None:
        raise ValueError("data.source.path is not set: point it at an .npz with 'positions' [S, T, N, 2] "
                         "(optional 'velocities', 'mask', 'edges')")
    data = load_trajectories(Path(path).expanduser(), frame_rate)
    count = data["states"].shape[0]
    ids = {"clip": torch.arange(count), "frame": torch.full((count,), int(data["first_frame"]), dtype=torch.long)}
    return Clips(data["states"], data["mask"], data.get("edges"), ids, data["origin"])
