"""Duration plugins: how each edge's time axis is cut into segments of one interaction type.

Every plugin offers
- ``segment(h_fwd, h_rev, x) -> Segmentation`` for training and posterior inference over a whole clip,
- ``next_duration(h_t, t, end) -> [B, E] long`` for online inference and roll-outs: when an edge's
  segment ends at step t, how many steps its next segment lasts (read from the past only).

Shapes: h_fwd, h_rev [B, E, T, R]; x [B, T+1, N, D]; h_t [B, E, R].
"""

from __future__ import annotations

import torch
from torch import nn

from dider.models.segments import Segmentation


class PerStepDuration(nn.Module):
    """DNRI: every step is its own segment (K = T slots of length 1)."""

    def segment(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, x: torch.Tensor) -> Segmentation:
        b, e, t, _ = h_fwd.shape
        start = torch.arange(t, device=h_fwd.device).expand(b, e, t)
        valid = torch.ones(b, e, t, dtype=torch.bool, device=h_fwd.device)
        return Segmentation(start, valid, None, h_fwd.new_zeros(b))

    def next_duration(self, h_t: torch.Tensor, t: int, end: int) -> torch.Tensor:
        return torch.ones(h_t.shape[:2], dtype=torch.long, device=h_t.device)


class StaticDuration(nn.Module):
    """NRI-style static graph: one segment per edge covering the whole clip."""

    def segment(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, x: torch.Tensor) -> Segmentation:
        b, e, t, _ = h_fwd.shape
        start = torch.zeros(b, e, 1, dtype=torch.long, device=h_fwd.device)
        valid = torch.ones(b, e, 1, dtype=torch.bool, device=h_fwd.device)
        assign = h_fwd.new_ones(b, e, t, 1)
        return Segmentation(start, valid, assign, h_fwd.new_zeros(b))

    def next_duration(self, h_t: torch.Tensor, t: int, end: int) -> torch.Tensor:
        return torch.full(h_t.shape[:2], max(end - t, 1), dtype=torch.long, device=h_t.device)
