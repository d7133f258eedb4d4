"""Baseline decoder plugin :class:`ConstantVelocity`: each agent keeps its last displacement (no
parameters, edges ignored), the trivial forecast a relational model must beat
(``model=constant_velocity``). The other baseline, the learned decoder with every edge switched off
(``model=static_decoder``), is the ``decoder_edges: false`` setting of
:class:`~dider.models.vae.RelationalVAE`, so it works with any decoder.

Shapes: x [B, T, N, D] (positions first, then velocities), z [B, T, E, K], mask [B, T, N] bool or
None.
"""

from __future__ import annotations

import torch
from torch import nn


class ConstantVelocity(nn.Module):
    """x_{t+1} = (p_t + (p_t - p_{t-1}), v_t): the last displacement carried on, velocity features
    held.

    Works in normalised units unchanged (min/max normalisation is affine, so a displacement
    normalises to the same displacement). An agent's first present frame has no displacement (it is
    held in place).
    """

    stateless = False

    def __init__(self, **unused: object) -> None:
        """Takes (and ignores) any decoder's settings: the model config sets only ``_target_`` over
        the decoder an experiment selects, so its width and the like stay in the merged config."""
        super().__init__()

    @staticmethod
    def _next(x: torch.Tensor, prev: torch.Tensor, has_prev: torch.Tensor) -> torch.Tensor:
        step = (x[..., :2] - prev[..., :2]) * has_prev.unsqueeze(-1).to(x.dtype)
        return torch.cat([x[..., :2] + step, x[..., 2:]], dim=-1)

    def forward(self, x: torch.Tensor, z: torch.Tensor,
                mask: torch.Tensor | None = None) -> torch.Tensor:
        """Teacher-forced: x [B, T, N, D] -> predictions of x_1..x_T [B, T, N, D] (z is ignored)."""
        prev = torch.cat([x[:, :1], x[:, :-1]], dim=1)
        has_prev = torch.ones(x.shape[:-1], dtype=torch.bool, device=x.device)
        has_prev[:, 0] = False
        if mask is not None:
            has_prev[:, 1:] &= mask[:, :-1]
        return self._next(x, prev, has_prev)

    def init_state(self, batch: int, num_agents: int,
                   ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(previous frame [B, N, D], whether it was present [B, N])."""
        return (torch.zeros(batch, num_agents, ref.shape[-1], dtype=ref.dtype, device=ref.device),
                torch.zeros(batch, num_agents, dtype=torch.bool, device=ref.device))

    def step(self, x_t: torch.Tensor, z_t: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor],
             mask_t: torch.Tensor | None = None) -> tuple[torch.Tensor,
                                                          tuple[torch.Tensor, torch.Tensor]]:
        prev, had = state
        present = torch.ones_like(had) if mask_t is None else mask_t
        return self._next(x_t, prev, had & present), (x_t, present)
