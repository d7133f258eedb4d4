"""Loss terms of the relational VAE.

Shapes: pred/target [B, T, N, D]; mask [B, T, N] bool; logits [..., K].
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def gaussian_nll_each(pred: torch.Tensor, target: torch.Tensor,
                      variance: float | torch.Tensor) -> torch.Tensor:
    """Each agent-step's fixed-variance Gaussian NLL, summed over features: pred, target [..., D] ->
    [...]."""
    if isinstance(variance, torch.Tensor) and variance.dim() > 0:  # one per feature
        var = variance.to(torch.promote_types(pred.dtype, torch.float32))
        return (((pred - target).pow(2) / (2 * var)).sum(-1)
                + 0.5 * torch.log(2 * math.pi * var).sum())
    v, d = float(variance), pred.shape[-1]
    return (pred - target).pow(2).sum(-1) / (2 * v) + 0.5 * d * math.log(2 * math.pi * v)


def gaussian_nll(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
                 variance: float | torch.Tensor) -> torch.Tensor:
    """Fixed-variance Gaussian NLL per sample: sum over features, mean over present (step,
    agent). -> [B]. ``variance``: one for every feature, or one per feature ([D]).

    The log-normaliser is counted once per feature (a proper Gaussian); DNRI counted it once per
    agent, which only shifts the reported value by a constant.
    """
    per_agent = gaussian_nll_each(pred, target, variance)
    m = mask.to(per_agent.dtype)
    return (per_agent * m).flatten(1).sum(1) / m.flatten(1).sum(1).clamp_min(1.0)


def categorical_kl(q_logits: torch.Tensor, p_logits: torch.Tensor) -> torch.Tensor:
    """KL(q || p) between categoricals given by logits: [..., K] -> [...]."""
    log_q = F.log_softmax(q_logits, dim=-1)
    return (log_q.exp() * (log_q - F.log_softmax(p_logits, dim=-1))).sum(-1)


def categorical_kl_probs(q: torch.Tensor, log_p: torch.Tensor) -> torch.Tensor:
    """KL(q || p) with q given by probabilities (0 log 0 = 0) and p by log-probabilities: [...,
    K] -> [...]."""
    return (q * (q.clamp_min(1e-16).log() - log_p)).sum(-1)


def gaussian_kl(mu: torch.Tensor, sigma: torch.Tensor, mu0: float, sigma0: float) -> torch.Tensor:
    """KL(N(mu, sigma^2) || N(mu0, sigma0^2)), elementwise."""
    return torch.log(sigma0 / sigma) + (sigma.pow(2) + (mu - mu0).pow(2)) / (2 * sigma0**2) - 0.5


def capacity(step: int, c_max: float, ramp_steps: int) -> float:
    """Capacity C ramped linearly from 0 to ``c_max`` over ``ramp_steps`` optimiser steps (Burgess
    et al.)."""
    if ramp_steps <= 0:
        return c_max
    return c_max * min(1.0, step / ramp_steps)


def line_fit(v: torch.Tensor, dp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Least squares of dp on v (flat tensors of equal length, v not constant): (slope, offset)."""
    slope = ((v - v.mean()) * (dp - dp.mean())).mean() / ((v - v.mean()) ** 2).mean()
    return slope, dp.mean() - slope * v.mean()


def residual_variance(x: torch.Tensor, mask: torch.Tensor | None = None,
                      floor: float = 1e-8) -> torch.Tensor:
    """Per feature, the variance of what one step of constant velocity leaves unexplained: x [B, T,
    N, D] with positions and velocities first (D >= 4; the position moves by a least-squares
    multiple of the velocity, which absorbs the step and the two normalisations), or any features (D
    < 4: the change from one step to the next); over the agents present at both ends (mask [B, T,
    N]). -> [D], at least ``floor`` and a millionth of the feature's own variance (a feature
    constant velocity explains exactly must not weigh millions of times the others); 1 for every
    feature without two such steps."""
    x = x.float()
    both = (torch.ones_like(x[..., 0], dtype=torch.bool) if mask is None else mask.bool())
    both = both[:, 1:] & both[:, :-1]
    now, nxt = x[:, :-1][both], x[:, 1:][both]  # [M, D]
    if len(now) < 2:
        return torch.ones_like(x[0, 0, 0])
    change = nxt - now
    if x.shape[-1] >= 4 and now[:, 2:4].var() > 0:
        slope, offset = line_fit(now[:, 2:4].flatten(), change[:, :2].flatten())
        change[:, :2] -= slope * now[:, 2:4] + offset
    return change.var(0).clamp_min(floor).maximum(1e-6 * now.var(0))
