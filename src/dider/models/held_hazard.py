"""The online boundary model of DIDER's segments: the prior hazard that a segment ends at step t,
given what the past shows there (the forward LSTM state), the type the segment holds and its age,
p(end at t | z_k, t - s_k, h_fwd_t) = sigmoid(a_{z_k}(h_fwd_t) + g_{z_k}(t - s_k)), as
explicit-duration switching models have it: a segment of one interaction lasts as that interaction
does.

``held=False`` is the hazard of the past alone (one output, no age term): what the prior read
before.

Shapes: B batch, E edges, T transitions, R LSTM width, K edge types (K' = K, or 1 without ``held``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from dider.models.end_categorical import OFFSET_SCALES, offset_features
from dider.models.layers import SumLinear


class HeldHazard(nn.Module):
    """a_k(h) for each held type k (an MLP of the past state, K' outputs) plus g_k(age) (a linear
    read of the age's log-scale bumps, :func:`offset_features`)."""

    def __init__(self, rnn_hidden: int, hidden: int, num_types: int, held: bool,
                 rate_logit: float) -> None:
        super().__init__()
        self.held = held
        width = num_types if held else 1
        self.past = nn.Sequential(nn.Linear(rnn_hidden, hidden), nn.ELU(), SumLinear(hidden, width))
        self.age = SumLinear(len(OFFSET_SCALES), width) if held else None
        with torch.no_grad():  # start at the fixed rate: segments of about 1 / rate steps
            self.past[-1].bias.fill_(rate_logit)

    @property
    def width(self) -> int:
        return self.past[-1].out_features

    def steps(self, h_fwd: torch.Tensor) -> torch.Tensor:
        """h_fwd [..., R] -> [..., K'] fp32 (the logits feed KL terms and a threshold)."""
        return self.past(h_fwd).float()

    def ages(self, age: torch.Tensor) -> torch.Tensor:
        """age [...] long (steps since the segment's start) -> [..., K'] (zeros without
        ``held``)."""
        if self.age is None:
            return torch.zeros(*age.shape, 1, device=age.device)
        return self.age(offset_features(age.clamp_min(0))).float()

    def of_start(self, steps: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
        """Each type's hazard at every step of a segment that started at ``start``: steps [B, E, T,
        K'] (of :meth:`steps`), start [B, E] long -> [B, E, K', T]; or of every candidate start at
        once (``start`` [S] long, S = T) -> [B, E, S, K', T]."""
        t = steps.shape[2]
        step = torch.arange(t, device=steps.device)
        if start.dim() == 1:
            table = self.ages(step)  # [T, K']: one row per age
            age = table[(step.view(1, -1) - start.view(-1, 1)).clamp_min(0)]  # [S, T, K']
            return (steps.unsqueeze(2) + age).transpose(-1, -2)
        return (steps + self.ages(step - start.unsqueeze(-1))).transpose(-1, -2)

    def at(self, h_t: torch.Tensor, held: torch.Tensor | None,
           age: torch.Tensor | None) -> torch.Tensor:
        """Online, at one step: h_t [B, E, R], the held type and the segment's age [B, E] long ->
        [B, E] logits."""
        logits = self.steps(h_t)
        if not self.held or held is None:
            return logits[..., 0] if not self.held else logits.mean(-1)
        chosen = logits.gather(-1, held.unsqueeze(-1)).squeeze(-1)
        return chosen + self.ages(age).gather(-1, held.unsqueeze(-1)).squeeze(-1)

    def along(self, h_fwd: torch.Tensor, held: torch.Tensor, starts: torch.Tensor) -> torch.Tensor:
        """The hazard at every step t of a given cut, of the segment that holds t-1: h_fwd [B, E, T,
        R], held [B, E, T] long (each step's type), starts [B, E, T] bool (where the cut starts a
        segment) -> [B, E, T] (step 0's is that of its own segment: never read)."""
        t = h_fwd.shape[2]
        step = torch.arange(t, device=h_fwd.device)
        # the start of the segment holding each step
        run_start = torch.where(starts, step, 0).cummax(-1).values
        before = F.pad(run_start[..., :-1], (1, 0))  # ... holding t - 1
        prev = F.pad(held[..., :-1], (1, 0)) if self.held else torch.zeros_like(held)
        logits = self.steps(h_fwd) + self.ages(step - before)  # [B, E, T, K']
        return logits.gather(-1, prev.unsqueeze(-1)).squeeze(-1)
