"""What a clip source gives the data module: :class:`Clips`, a split of fixed-length clips already cut (the
simulators, and the files that ship clips: NRI's, DNRI's, the basketball sets, ``.npz`` trajectories)."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Clips:
    """One split's clips, raw (not normalised). states: [S, T, N, 4] float32 (x, y, vx, vy); mask: [S, T, N] bool
    or None (every agent present); edges: [S, T-1, E] long, the type of each transition t -> t+1, or None; ids: the
    clips' source identifiers ([S] or [S, N] long each) or None."""

    states: torch.Tensor
    mask: torch.Tensor | None = None
    edges: torch.Tensor | None = None
    ids: dict[str, torch.Tensor] | None = None

    def __len__(self) -> int:
        return self.states.shape[0]
