"""A hold gate: each edge's segments end where a per-step boundary fires, not after a drawn duration.

A departure from the paper's duration latent (``model=dider_gate``; docs/results.md says why it was built).
At every transition t of an edge a boundary b_t in {0, 1} says whether a new segment starts there; the edge
type held at t is the one drawn at the last boundary, z_t = b_t y_t + (1 - b_t) z_{t-1}.

Shapes: B batch, E edges, T transitions, R LSTM width, S = T slots (slot s is the segment starting at s).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from dider.losses import categorical_kl
from dider.models.plugins import Progress
from dider.models.segments import Segmentation, entries
from dider.validation import require


def bernoulli_kl(q_logits: torch.Tensor, p_logits: torch.Tensor) -> torch.Tensor:
    """KL(q || p) between Bernoullis given by the logits of their 1: [...] -> [...]."""
    zero = torch.zeros_like(q_logits)
    return categorical_kl(torch.stack([q_logits, zero], -1), torch.stack([p_logits.expand_as(q_logits), zero], -1))


def hold_assignment(gate: torch.Tensor) -> torch.Tensor:
    """Boundaries [B, E, T] (gate[..., 0] = 1) -> step-to-slot assignment [B, E, T, S=T]: step t belongs to the
    slot of the last boundary at or before it.

    The assignment is built by the recurrence z_t = b_t e_t + (1 - b_t) z_{t-1} (e_t the one-hot of slot t),
    so a straight-through gate (0 or 1 forward) gets, at each step, the gradient of switching the held type
    there: the new segment's type against the one held before it. Without gradients, the one-hot directly."""
    b, e, t = gate.shape
    if not torch.is_grad_enabled() or not gate.requires_grad:
        step = torch.arange(t, device=gate.device)
        slot = torch.where(gate.detach() > 0.5, step, 0).cummax(-1).values  # the last boundary at or before t
        return nn.functional.one_hot(slot, t).to(gate.dtype)
    eye = torch.eye(t, device=gate.device, dtype=gate.dtype)
    rows = [eye[0].expand(b, e, t) * gate[..., :1]]
    for j in range(1, t):  # over steps only, vectorised over batch, edges and slots
        g = gate[..., j, None]
        rows.append(g * eye[j] + (1 - g) * rows[-1])
    return torch.stack(rows, dim=2)


class HoldGate(nn.Module):
    """A per-step boundary latent: a segment lasts until the next boundary fires.

    - Posterior: b_t ~ Bernoulli(sigmoid(f_q([h_fwd_t, h_rev_t]))), reading the past and the remaining
      trajectory; trained through a relaxed Bernoulli at ``temperature``, straight-through (exactly 0 or 1
      forward; ``sample=false``: the posterior's mode, as evaluation takes).
    - Prior: a learned gate f_p(h_fwd_t), past only, mixed with a fixed boundary ``rate``: the duration KL is
      (1 - ``rate_mix``) KL(q_t || p_t) + ``rate_mix`` KL(q_t || rate), summed over an edge's steps and divided
      by them (the edge KL's convention). The rate is what makes a boundary cost something; the learned gate
      is what forecasting uses.
    - The edge KL of a segment is counted at its boundary, weighted by the straight-through gate
      (``Segmentation.weight``), so a boundary also pays for the edge type it draws.
    - Online (forecasting, prior types): a new segment starts where the prior gate's probability exceeds
      ``online_threshold`` (``boundary``); otherwise the type is held.
    - ``burn_in``: transitions 0..burn_in-2 are one observed segment, and a segment starts at the first
      forecast transition, read from the whole burn-in (as DIDER's duration does); null: the gate is free
      from transition 1 on.
    - Agents that come and go (``present``): a segment starts where an edge enters (its two agents present
      again), in training and online, so no segment's type is read while the edge is absent and every
      segment's edge KL is counted; absent steps have no boundary and no gate KL, and the gate KL is
      divided by the present edge-steps.
    """

    def __init__(
        self,
        rnn_hidden: int = 64,
        hidden: int = 64,
        rate: float = 0.2,
        rate_mix: float = 0.5,
        temperature: float = 0.5,
        sample: bool = True,
        online_threshold: float = 0.5,
        burn_in: int | None = None,
    ) -> None:
        super().__init__()
        require({"model.duration.rate": rate, "model.duration.rate_mix": rate_mix,
                 "model.duration.temperature": temperature, "model.duration.sample": sample,
                 "model.duration.online_threshold": online_threshold, "model.duration.burn_in": burn_in})
        self.rate_logit, self.rate_mix, self.temperature = math.log(rate / (1 - rate)), rate_mix, temperature
        self.sample, self.online_threshold = sample, online_threshold
        self.observed = 0 if burn_in is None else burn_in - 1
        self.posterior = nn.Sequential(nn.Linear(2 * rnn_hidden, hidden), nn.ELU(), nn.Linear(hidden, 1))
        self.prior = nn.Sequential(nn.Linear(rnn_hidden, hidden), nn.ELU(), nn.Linear(hidden, 1))

    def forced(self, t: int, device: torch.device,
               present: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Steps whose boundary is fixed, and the fixed value, [T] bool each, or [B, E, T] with ``present``
        [B, E, T] bool: a boundary at step 0, where the forecast starts and where an edge enters; none
        inside the burn-in or where the edge is absent."""
        step = torch.arange(t, device=device)
        fixed, value = step <= self.observed, (step == 0) | (step == self.observed)
        if present is None:
            return fixed, value
        entered = entries(present)
        value = (value | entered) & (present | (step == 0))  # step 0 opens the first slot even when absent
        return fixed | entered | ~present, value

    def segment(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, x: torch.Tensor,
                progress: Progress = Progress(), present: torch.Tensor | None = None) -> Segmentation:
        b, e, t, _ = h_fwd.shape
        # fp32 under autocast: the logits feed KL terms and a threshold
        q = self.posterior(torch.cat([h_fwd, h_rev], -1)).squeeze(-1).float()  # [B, E, T]
        p = self.prior(h_fwd).squeeze(-1).float()
        if self.training and self.sample:
            u = torch.rand_like(q).clamp(1e-6, 1 - 1e-6)
            q_noisy = q + u.log() - (-u).log1p()  # + logistic noise: the relaxed Bernoulli
        else:
            q_noisy = q
        soft = torch.sigmoid(q_noisy / self.temperature)
        gate = (soft > 0.5).float() + soft - soft.detach()
        fixed, value = self.forced(t, h_fwd.device, present)
        gate = torch.where(fixed, value.float(), gate)
        kl = (1 - self.rate_mix) * bernoulli_kl(q, p) + self.rate_mix * bernoulli_kl(q, q.new_tensor(self.rate_logit))
        steps = e * t if present is None else present.flatten(1).sum(1).clamp_min(1)
        kl = (kl * ~fixed).flatten(1).sum(1) / steps
        start = torch.arange(t, device=h_fwd.device).expand(b, e, t)
        return Segmentation(start, gate.detach() > 0.5, hold_assignment(gate), kl, weight=gate)

    def next_duration(self, h_t: torch.Tensor, t: int, end: int) -> torch.Tensor:
        """Inside the burn-in: its span ends where the forecast starts. Otherwise a segment holds to the end
        unless :meth:`boundary` fires first."""
        left = self.observed - t if t < self.observed else end - t
        return torch.full(h_t.shape[:2], left, dtype=torch.long, device=h_t.device)

    def boundary(self, h_t: torch.Tensor, t: int, end: int) -> torch.Tensor:
        """Online: [B, E] bool, where a new segment starts at step t: after the burn-in, where the prior gate
        (past only) fires. Where an edge enters, the roll-out's state machine reads a new type anyway
        (:meth:`RelationalVAE.advance_edges`), and a gate segment lasts to the next boundary either way."""
        if t <= self.observed:
            return torch.zeros(h_t.shape[:2], dtype=torch.bool, device=h_t.device)
        return torch.sigmoid(self.prior(h_t).squeeze(-1).float()) > self.online_threshold
