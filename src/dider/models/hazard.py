"""What the boundary-based duration plugins share: a past-only boundary hazard as the prior, the
boundaries that are fixed (the clip's start, the burn-in, where an edge enters), the held assignment
and the online rule.

A segment's duration distribution p(d) is equivalently a hazard h_c = P(d = c | d >= c): the prior
here gives a hazard at every step from the past (the forward LSTM state), mixed with a fixed
boundary ``rate``, so forecasting needs nothing but the past: a new segment starts where the prior's
hazard exceeds a threshold.

Shapes: B batch, E edges, T transitions, R LSTM width, S = T slots (slot s is the segment starting
at s).
"""

from __future__ import annotations

import math
from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import nn

from dider.models.layers import SumLinear
from dider.models.losses import categorical_kl
from dider.models.segments import forced_boundaries
from dider.validation import Rule, at_least, integer, optional, within, within_open


def bernoulli_kl(q_logits: torch.Tensor, p_logits: torch.Tensor) -> torch.Tensor:
    """KL(q || p) between Bernoullis given by the logits of their 1: [...] -> [...]."""
    zero = torch.zeros_like(q_logits)
    return categorical_kl(torch.stack([q_logits, zero], -1),
                          torch.stack([p_logits.expand_as(q_logits), zero], -1))


def hold_assignment(gate: torch.Tensor, closed: bool | None = None) -> torch.Tensor:
    """Boundaries [B, E, T] (gate[..., 0] = 1) -> step-to-slot assignment [B, E, T, S=T]: step t
    belongs to the slot of the last boundary at or before it.

    The assignment is built by the recurrence z_t = b_t e_t + (1 - b_t) z_{t-1} (e_t the one-hot of
    slot t), so a straight-through gate (0 or 1 forward) gets, at each step, the gradient of
    switching the held type there: the new segment's type against the one held before it. Without
    gradients, the one-hot directly. ``closed``: the recurrence unrolled as one cumulative product
    (True) or run step by step (False); None picks by device: on a GPU the loop's small kernels cost
    more than the [B, E, T, T] product, on a CPU the product's backward through the gate's zeros
    costs more than the loop (docs/performance.md)."""
    b, e, t = gate.shape
    if not torch.is_grad_enabled() or not gate.requires_grad:
        step = torch.arange(t, device=gate.device)
        # the last boundary at or before t
        slot = torch.where(gate.detach() > 0.5, step, 0).cummax(-1).values
        return nn.functional.one_hot(slot, t).to(gate.dtype)
    if gate.is_cuda if closed is None else closed:
        return _held_closed(gate)
    eye = torch.eye(t, device=gate.device, dtype=gate.dtype)
    rows = [eye[0].expand(b, e, t) * gate[..., :1]]
    for j in range(1, t):  # over steps only, vectorised over batch, edges and slots
        g = gate[..., j, None]
        rows.append(g * eye[j] + (1 - g) * rows[-1])
    return torch.stack(rows, dim=2)


class SyncFreeCumprod(torch.autograd.Function):
    """``x.cumprod(dim)`` with a backward that never reads a value back. Torch's own backward asks
    the host whether the input holds a zero (a synchronisation a CUDA graph cannot hold) and then
    takes data-dependent masks; here both cases are one dense formula. For y = cumprod(x) and
    incoming gradient g, along dim: before the slice's first zero z, dx_k = sum_{k <= j < z} g_j y_j
    / x_k; at z, dx_z = sum_{j >= z} g_j prod_{i <= j, i != z} x_i (the cumulative product with x_z
    read as 1); after it, 0."""

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, x: torch.Tensor,
                dim: int) -> torch.Tensor:
        y = x.cumprod(dim)
        ctx.save_for_backward(x, y)
        ctx.dim = dim
        return y

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx,
                 g: torch.Tensor) -> tuple[torch.Tensor, None]:
        x, y = ctx.saved_tensors
        d = ctx.dim
        zero = x == 0
        zeros_so_far = zero.cumsum(d)
        before, first = zeros_so_far == 0, zero & (zeros_so_far == 1)

        def from_here(v: torch.Tensor) -> torch.Tensor:  # sum over j >= k
            return v.flip(d).cumsum(d).flip(d)

        dx = torch.where(before,
                         from_here(torch.where(before, g * y, 0.0)) / torch.where(before, x, 1.0),
                         0.0)
        at_first = from_here(g * torch.where(first, 1.0, x).cumprod(d))
        return torch.where(first, at_first, dx), None


def _held_closed(gate: torch.Tensor) -> torch.Tensor:
    """The recurrence of :func:`hold_assignment` unrolled: z_t[s] = b_s prod_{s < j <= t} (1 - b_j)
    for s <= t, else
    0. gate [B, E, T] -> [B, E, T, S=T]."""
    t = gate.shape[-1]
    upto = torch.ones(t, t, dtype=torch.bool, device=gate.device).tril()  # [t, s]: s <= t
    later = upto.tril(-1)  # s < t: the steps whose (1 - b_t) a segment started at s survives
    # [B, E, T, S]: prod over s < j <= t
    held = SyncFreeCumprod.apply(torch.where(later, (1 - gate).unsqueeze(-1), 1.0), -2)
    return torch.where(upto, gate.unsqueeze(-2) * held, 0.0)


class HazardPrior(nn.Module):
    """The prior boundary hazard, the fixed boundaries and the online rule of a boundary-based
    duration plugin.

    - The prior: a learned hazard f_p(h_fwd_t) (past only) at every step; a duration KL is (1 -
      ``rate_mix``) KL(q || learned) + ``rate_mix`` KL(q || the fixed ``rate``). The rate is what
      makes a boundary cost something; the learned hazard is what forecasting uses.
    - Online (forecasting, prior types): a new segment starts where the learned hazard exceeds
      ``online_threshold`` (:meth:`boundary`); otherwise the type is held.
    - ``burn_in``: transitions 0..burn_in-2 are one observed segment, and a segment starts at the
      first forecast transition, read from the whole burn-in; null: boundaries are free from
      transition 1 on.
    - Agents that come and go (``present``): a segment starts where an edge enters (its two agents
      present again); absent steps have no boundary.
    """

    SETTINGS: ClassVar[dict[str, Rule]] = {
        "rnn_hidden": integer(1), "hidden": integer(1), "rate": within_open(0.0, 1.0),
        "rate_mix": within(0.0, 1.0),
        "online_threshold": within_open(0.0, 1.0), "burn_in": optional(at_least(1)),
    }

    def __init__(self, rnn_hidden: int, hidden: int, rate: float, rate_mix: float,
                 online_threshold: float, burn_in: int | None) -> None:
        super().__init__()
        self.rate_logit, self.rate_mix = math.log(rate / (1 - rate)), rate_mix
        self.online_threshold = online_threshold
        self.observed = 0 if burn_in is None else burn_in - 1
        self.prior = nn.Sequential(nn.Linear(rnn_hidden, hidden), nn.ELU(), SumLinear(hidden, 1))

    def prior_logits(self, h_fwd: torch.Tensor) -> torch.Tensor:
        """h_fwd [..., R] -> [...] the learned prior hazard's logits (fp32: they feed KL terms and a
        threshold)."""
        return self.prior(h_fwd).squeeze(-1).float()

    def forced(self, t: int, device: torch.device,
               present: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Steps whose boundary is fixed, and the fixed value
        (:func:`~dider.models.segments.forced_boundaries`)."""
        return forced_boundaries(t, self.observed, device, present)

    def cut_kl(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, gate: torch.Tensor,
               free: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
        """The duration KL of a posterior certain of a given cut: -log p(cut) under the prior, mixed
        as the duration KL is. gate [B, E, T] bool (a segment starts at each true step), free [B, E,
        T] bool (the steps whose boundary is not fixed), steps [B] (present edge-steps) -> [B]."""
        b = gate.float()

        def nll(logits: torch.Tensor) -> torch.Tensor:
            return -(b * F.logsigmoid(logits) + (1 - b) * F.logsigmoid(-logits))

        p = self.prior_logits(h_fwd)
        per_step = ((1 - self.rate_mix) * nll(p)
                    + self.rate_mix * nll(torch.full_like(p, self.rate_logit)))
        return (per_step * free).flatten(1).sum(1) / steps

    def next_duration(self, h_t: torch.Tensor, t: int, end: int) -> torch.Tensor:
        """Inside the burn-in: its span ends where the forecast starts. Otherwise a segment holds to
        the end unless :meth:`boundary` fires first."""
        left = self.observed - t if t < self.observed else end - t
        return torch.full(h_t.shape[:2], left, dtype=torch.long, device=h_t.device)

    def boundary(self, h_t: torch.Tensor, t: int, end: int, draw: bool = False) -> torch.Tensor:
        """Online: [B, E] bool, where a new segment starts at step t: after the burn-in, where the
        prior hazard (past only) exceeds ``online_threshold`` (``draw``: with the hazard's
        probability, a sampled future). Where an edge enters, the roll-out's state machine reads a
        new type anyway (:meth:`RelationalVAE.advance_edges`), and a segment lasts to the next
        boundary."""
        if t <= self.observed:
            return torch.zeros(h_t.shape[:2], dtype=torch.bool, device=h_t.device)
        return fires(torch.sigmoid(self.prior_logits(h_t)), self.online_threshold, draw)


def fires(p: torch.Tensor, threshold: float, draw: bool) -> torch.Tensor:
    """A boundary with probability ``p``: drawn (a sampled future), or where p passes
    ``threshold``."""
    return torch.rand_like(p) < p if draw else p > threshold
