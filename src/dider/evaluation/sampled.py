"""Scoring sampled futures as the trajectory-forecasting field does: of K forecasts per clip, the
best one per agent.

For each agent and horizon h, over K sampled roll-outs: minADE_K is the smallest, over the samples,
mean displacement of its scored frames up to horizon h; minFDE_K the smallest displacement at
horizon h; the miss rate the share of agents whose minFDE_K exceeds a threshold (data units). Each
is averaged over the agents that reach the horizon (a scored frame at h; for minADE, one at h or
before). A model whose edges are latent variables forecasts a distribution, which one deterministic
roll-out cannot show.

Shapes: B clips, K samples, P predicted steps, N agents, D features, H horizons.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torchmetrics import Metric

from dider.evaluation.metrics import horizon_list


class MinDisplacement(Metric):
    """update(pred [B, K, P, N, D], target [B, P, N, D], mask [B, P, N] bool (the scored frames),
    horizon [B, P, N] long or None: as :class:`~dider.evaluation.metrics.HorizonDisplacement`'s);
    compute() -> [3, H]: minADE_K, minFDE_K and the miss rate (minFDE_K > ``miss_threshold``; NaN
    without a threshold), NaN at a horizon no agent reached."""

    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(self, horizons: Sequence[int], miss_threshold: float | None = None,
                 **kwargs) -> None:
        super().__init__(**kwargs)
        self.horizons = horizon_list(horizons)
        self.miss_threshold = miss_threshold
        for name in ("ade", "fde", "miss", "ade_agents", "fde_agents"):
            self.add_state(name, torch.zeros(len(self.horizons), dtype=torch.float64),
                           dist_reduce_fx="sum")

    def update(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
               horizon: torch.Tensor | None = None) -> None:
        if max(self.horizons) > pred.shape[2]:
            raise ValueError(f"horizon {max(self.horizons)} exceeds the {pred.shape[2]} predicted "
                             "steps")
        if horizon is None:
            horizon = (torch.arange(1, mask.shape[1] + 1, device=mask.device).view(1, -1, 1)
                       .expand_as(mask))
        # [B, K, P, N]
        dist = (pred[..., :2].double() - target.unsqueeze(1)[..., :2].double()).norm(dim=-1)
        scored = mask & (horizon >= 1)
        for i, h in enumerate(self.horizons):
            upto = (scored & (horizon <= h)).unsqueeze(1)  # [B, 1, P, N]
            steps = upto.sum(2)  # [B, 1, N]
            ade = torch.where(upto, dist, 0.0).sum(2) / steps.clamp_min(1)  # [B, K, N]
            at = (scored & (horizon == h)).unsqueeze(1)
            fde = torch.where(at, dist, 0.0).sum(2)  # [B, K, N]: the one frame at horizon h
            reach_ade, reach_fde = steps[:, 0] > 0, at.any(2)[:, 0]  # [B, N]
            best_ade, best_fde = ade.min(1).values, fde.min(1).values  # [B, N]
            self.ade[i] += best_ade[reach_ade].sum()
            self.ade_agents[i] += reach_ade.sum()
            self.fde[i] += best_fde[reach_fde].sum()
            self.fde_agents[i] += reach_fde.sum()
            if self.miss_threshold is not None:
                self.miss[i] += (best_fde[reach_fde] > self.miss_threshold).sum()

    def compute(self) -> torch.Tensor:
        nan = torch.full_like(self.miss, float("nan"))
        miss = self.miss / self.fde_agents if self.miss_threshold is not None else nan
        return torch.stack([self.ade / self.ade_agents, self.fde / self.fde_agents, miss]).float()


def sampled_values(prefix: str, metric: MinDisplacement, samples: int) -> dict[str, torch.Tensor]:
    """``prefix/min_ade_K/hXX``, ``prefix/min_fde_K/hXX`` and, with a threshold,
    ``prefix/miss_rate_K/hXX``."""
    ade, fde, miss = metric.compute()
    out: dict[str, torch.Tensor] = {}
    for h, a, f, m in zip(metric.horizons, ade, fde, miss, strict=True):
        out[f"{prefix}/min_ade_{samples}/h{h:02d}"] = a
        out[f"{prefix}/min_fde_{samples}/h{h:02d}"] = f
        if metric.miss_threshold is not None:
            out[f"{prefix}/miss_rate_{samples}/h{h:02d}"] = m
    return out
