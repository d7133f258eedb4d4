"""Loss terms of the relational VAE.

Shapes: pred/target [B, T, N, D]; mask [B, T, N] bool; logits [..., K].
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def gaussian_nll(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, variance: float) -> torch.Tensor:
    """Fixed-variance Gaussian NLL per sample: sum over features, mean over present (step, agent). -> [B].

    The log-normaliser is counted once per feature (a proper Gaussian); DNRI counted it once per agent,
    which only shifts the reported value by a constant.
    """
    d = pred.shape[-1]
    per_agent = (pred - target).pow(2).sum(-1) / (2 * variance) + 0.5 * d * math.log(2 * math.pi * variance)
    m = mask.to(per_agent.dtype)
    return (per_agent * m).flatten(1).sum(1) / m.flatten(1).sum(1).clamp_min(1.0)


def categorical_kl(q_logits: torch.Tensor, p_logits: torch.Tensor) -> torch.Tensor:
    """KL(q || p) between categoricals given by logits: [..., K] -> [...]."""
    log_q = F.log_softmax(q_logits, dim=-1)
    return (log_q.exp() * (log_q - F.log_softmax(p_logits, dim=-1))).sum(-1)


def categorical_kl_probs(q: torch.Tensor, log_p: torch.Tensor) -> torch.Tensor:
    """KL(q || p) with q given by probabilities (0 log 0 = 0) and p by log-probabilities: [..., K] -> [...]."""
    return (q * (q.clamp_min(1e-16).log() - log_p)).sum(-1)


def gaussian_kl(mu: torch.Tensor, sigma: torch.Tensor, mu0: float, sigma0: float) -> torch.Tensor:
    """KL(N(mu, sigma^2) || N(mu0, sigma0^2)), elementwise."""
    return torch.log(sigma0 / sigma) + (sigma.pow(2) + (mu - mu0).pow(2)) / (2 * sigma0**2) - 0.5


def capacity(step: int, c_max: float, ramp_steps: int) -> float:
    """Capacity C ramped linearly from 0 to ``c_max`` over ``ramp_steps`` optimiser steps (Burgess et al.)."""
    if ramp_steps <= 0:
        return c_max
    return c_max * min(1.0, step / ramp_steps)
