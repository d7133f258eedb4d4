"""The synthetic data files of the public DNRI code (cgraber/cvpr_dNRI, ``dnri/datasets/small_synth_data.py``).

A folder ``root`` holds six files written by ``torch.save``, without extension:

- ``{train,val,test}_feats``: [S, T, N, 4] float, (x, y, vx, vy) of every agent after each step;
- ``{train,val,test}_edges``: [S, T, N(N-1)] edge types (the DNRI generator saves them as float tensors
  of 0/1; integer tensors are accepted too). The edge order is ours (:mod:`dider.graph`): the off-diagonal
  of an N x N matrix, row-major, sender first. The generator marks particle 0 pushing particle 2 as edge 1
  and particle 1 pushing 2 as edge 3, which are (0, 2) and (1, 2) in that order; DNRI's models build
  their edge lists the same way (``np.where`` of a matrix with a zero diagonal).

Edge alignment. In the generator's loop over time steps, edge[t] is set from the distances between the
positions before the step's update; the pushed particle's velocity is then changed, every position is
advanced, and the result is stored as feats[t]. So raw edges[:, t] is the interaction that produced step t
from step t-1: the convention of our own simulator (:mod:`dider.data.simulators.push`). The clips carry
edges[:, 1:], [S, T-1, E], labelling the transitions t -> t+1 of the clip, as ``data=synth`` does. (The
DNRI code's own edge scoring, ``eval_edges`` in ``dnri/experiments/small_synth_experiment.py``, compares
its T-1 inferred edges with gt_edges[:, :-1], one step earlier; docs/journal/results_history.md discusses the
difference.)

Files are read with ``torch.load(weights_only=True)``: a file whose pickle would import anything but
tensors is refused, never run. Every problem raises naming the file.
"""

from __future__ import annotations

import pickle
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import torch

from dider.data.clip_source import Clips
from dider.data.common import SPLITS, check_finite
from dider.data.readers.folder import data_root
from dider.data.sources import SourceSettings
from dider.graph import num_edges
from dider.validation import Rule, one_of

# What torch.load raises on a file that is not a torch.save file (text, truncated, another format).
_READ_ERRORS = (pickle.UnpicklingError, RuntimeError, EOFError, KeyError, ValueError, OSError, AttributeError,
                IndexError, TypeError)


@dataclass(frozen=True)
class DNRIFiles(SourceSettings):
    """``data=dnri_files``'s ``data.source`` node."""

    root: str | None = None  # the folder holding the six files (required)
    predict_split: str = "test"  # the split whose files mode=predict reads

    FIT_ON_FILE: ClassVar[bool] = True  # DNRI fits the ranges on the whole training file, before any cap
    SETTINGS: ClassVar[dict[str, Rule]] = {"predict_split": one_of(*SPLITS)}

    def clips(self, sizes: Mapping[str, int | None], cache_dir: Path) -> dict[str, Clips]:
        return read(self.root)

    def predict_clips(self) -> Clips:
        """Every clip of the ``predict_split``'s files (``mode=predict``)."""
        return read(self.root, (self.predict_split,))[self.predict_split]

    def where(self) -> str:
        return f"data.source.root={self.root}"


def load_tensor(path: Path) -> torch.Tensor:
    """The tensor ``torch.save`` wrote to ``path``, loaded without running pickled code."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing (data.source.root must hold {{train,val,test}}_feats and _edges, "
                                f"as written by the DNRI code's small_synth_data.py)")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except _READ_ERRORS as e:
        lines = [line.strip() for line in str(e).splitlines() if line.strip()]
        # The weights-only unpickler names the global (a function or class) a payload wanted to import.
        if glob := next((line for line in lines if "global" in line.lower()), None):
            raise ValueError(f"{path}: refused: the file pickles objects other than tensors, which could run code "
                             f"when loaded ({glob}); save plain tensors, e.g. torch.from_numpy(array)") from None
        why = next((line for line in lines if line.startswith("Unsupported")), lines[0] if lines else "")
        raise ValueError(f"{path}: not a tensor file written by torch.save ({type(e).__name__}: {why})") from None
    if not isinstance(obj, torch.Tensor):
        raise ValueError(f"{path}: holds a {type(obj).__name__}, not a tensor")
    return obj


def load_split(root: Path, split: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Read and validate ``{split}_feats`` and ``{split}_edges`` -> feats [S, T, N, 4] float32 (raw) and
    edges [S, T, E] long (raw alignment: edges[:, t] produced step t from t-1)."""
    fpath, epath = root / f"{split}_feats", root / f"{split}_edges"
    feats, edges = load_tensor(fpath), load_tensor(epath)
    if feats.ndim != 4 or feats.shape[-1] != 4 or feats.numel() == 0:
        raise ValueError(f"{fpath}: shape {tuple(feats.shape)}; expected [S, T, N, 4] (x, y, vx, vy), non-empty")
    if feats.dtype == torch.bool or feats.is_complex():
        raise ValueError(f"{fpath}: dtype {feats.dtype}; expected real numbers")
    s, t, n, _ = feats.shape
    if n < 2 or t < 2:
        raise ValueError(f"{fpath}: {n} agent(s) and {t} step(s) per clip; need >= 2 of each")
    feats = feats.float()  # values beyond the float32 range become inf: reported below
    check_finite(f"{fpath}", feats)
    if edges.shape != (s, t, num_edges(n)):
        raise ValueError(f"{epath}: shape {tuple(edges.shape)}; expected [S, T, N(N-1)] = {(s, t, num_edges(n))} "
                         f"to match {fpath.name} {tuple(feats.shape)}")
    if edges.is_complex():
        raise ValueError(f"{epath}: dtype {edges.dtype}; expected integer edge types")
    edges = edges.long() if edges.dtype == torch.bool else edges
    if edges.is_floating_point():
        bad = ~torch.isfinite(edges) | (edges != edges.round())
        if bad.any():
            first = tuple(int(i) for i in bad.nonzero()[0])
            raise ValueError(f"{epath}: edge types must be integers (first bad value {edges[first].item()!r} at "
                             f"index {first})")
    if edges.numel() and (edges.min() < 0 or edges.max() >= 2**31):
        raise ValueError(f"{epath}: edge types must lie in 0..2**31-1 (found {edges.min().item()}.."
                         f"{edges.max().item()})")
    return feats, edges.long()


def read(root: str | Path | None, splits: Sequence[str] = SPLITS) -> dict[str, Clips]:
    """The ``splits`` of the folder ``root`` (``data.source.root``) as clips: edges[:, 1:] for the transitions t -> t+1,
    ids ``clip`` (the clip's index in its file)."""
    folder = data_root(root, "the folder with the DNRI code's train_feats, train_edges, val_feats, ... files")
    out = {}
    for split in splits:
        feats, edges = load_split(folder, split)
        out[split] = Clips(feats, edges=edges[:, 1:], ids={"clip": torch.arange(len(feats))})
    return out
