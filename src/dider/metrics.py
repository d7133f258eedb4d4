"""torchmetrics Metric classes (DDP-safe: every state is a sum)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torchmetrics import Metric


class HorizonMSE(Metric):
    """MSE at forecast horizons: the h-th predicted step, over present agents and all features.

    update(pred [B, P, N, D], target [B, P, N, D], mask [B, P, N] bool); compute() -> [len(horizons)].
    """

    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(self, horizons: Sequence[int], **kwargs) -> None:
        super().__init__(**kwargs)
        if not horizons or min(horizons) < 1:
            raise ValueError(f"horizons={list(horizons)}: need at least one horizon, each >= 1")
        self.horizons = [int(h) for h in horizons]
        self.add_state("sum_sq", torch.zeros(len(horizons), dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("count", torch.zeros(len(horizons), dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> None:
        if max(self.horizons) > pred.shape[1]:
            raise ValueError(f"horizon {max(self.horizons)} exceeds the {pred.shape[1]} predicted steps")
        idx = torch.tensor([h - 1 for h in self.horizons], device=pred.device)
        sq = (pred.index_select(1, idx) - target.index_select(1, idx)).pow(2).sum(-1)  # [B, H, N]
        m = mask.index_select(1, idx).to(sq.dtype)
        self.sum_sq += (sq * m).sum(dim=(0, 2)).double()
        self.count += (m.sum(dim=(0, 2)) * pred.shape[-1]).double()

    def compute(self) -> torch.Tensor:
        return (self.sum_sq / self.count.clamp_min(1)).float()


class EdgeAccuracy(Metric):
    """Recall per ground-truth class: "no interaction" (type 0) and "interaction" (any type > 0).

    Type 0 is pinned to "no interaction", so no permutation search is needed; with more than two learned
    types an interacting edge counts as found when any interaction type (> 0) is predicted.
    update(pred [..], target [..] long, mask [..] bool or None); compute() -> [2] (none, interaction).
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.add_state("correct", torch.zeros(2, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("total", torch.zeros(2, dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> None:
        truth, found = (target > 0).long(), (pred > 0).long()
        keep = torch.ones_like(truth, dtype=torch.bool) if mask is None else mask
        hit = (truth == found) & keep
        self.correct += torch.bincount(truth[hit], minlength=2).double()
        self.total += torch.bincount(truth[keep], minlength=2).double()

    def compute(self) -> torch.Tensor:
        return (self.correct / self.total.clamp_min(1)).float()
