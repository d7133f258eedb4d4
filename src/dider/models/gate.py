"""A hold gate: each edge's segments end where a per-step boundary fires, not after a drawn
duration.

A departure from the paper's duration latent (``model=dider_gate``; docs/journal/results_history.md
says why it was built). At every transition t of an edge a boundary b_t in {0, 1} says whether a new
segment starts there; the edge type held at t is the one drawn at the last boundary, z_t = b_t y_t +
(1 - b_t) z_{t-1}.

Shapes: B batch, E edges, T transitions, R LSTM width, S = T slots (slot s is the segment starting
at s).
"""

from __future__ import annotations

import torch
from torch import nn

from dider.models.hazard import HazardPrior, bernoulli_kl, hold_assignment
from dider.models.layers import SumLinear
from dider.models.plugins import Progress
from dider.models.segments import Segmentation
from dider.validation import above, boolean, check_settings


class HoldGate(HazardPrior):
    """A per-step boundary latent: a segment lasts until the next boundary fires.

    - Posterior: b_t ~ Bernoulli(sigmoid(f_q([h_fwd_t, h_rev_t]))), reading the past and the
      remaining trajectory; trained through a relaxed Bernoulli at ``temperature``, straight-through
      (exactly 0 or 1 forward; ``sample=false``: the posterior's mode, as evaluation takes).
    - Prior: a learned gate f_p(h_fwd_t), past only, mixed with a fixed boundary ``rate``: the
      duration KL is (1 - ``rate_mix``) KL(q_t || p_t) + ``rate_mix`` KL(q_t || rate), summed over
      an edge's steps and divided by them (the edge KL's convention). The rate is what makes a
      boundary cost something; the learned gate is what forecasting uses.
    - The edge KL of a segment is counted at its boundary, weighted by the straight-through gate
      (``Segmentation.weight``), so a boundary also pays for the edge type it draws.
    - Online (forecasting, prior types): a new segment starts where the prior gate's probability
      exceeds ``online_threshold`` (``boundary``); otherwise the type is held.
    - ``burn_in``: transitions 0..burn_in-2 are one observed segment, and a segment starts at the
      first forecast transition, read from the whole burn-in (as DIDER's duration does); null: the
      gate is free from transition 1 on.
    - Agents that come and go (``present``): a segment starts where an edge enters (its two agents
      present again), in training and online, so no segment's type is read while the edge is absent
      and every segment's edge KL is counted; absent steps have no boundary and no gate KL, and the
      gate KL is divided by the present edge-steps.
    """

    SETTINGS = HazardPrior.SETTINGS | {"temperature": above(0), "sample": boolean}

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
        check_settings(self, locals())
        super().__init__(rnn_hidden, hidden, rate, rate_mix, online_threshold, burn_in)
        self.temperature, self.sample = temperature, sample
        self.posterior = nn.Sequential(nn.Linear(2 * rnn_hidden, hidden), nn.ELU(),
                                       SumLinear(hidden, 1))

    def segment(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, x: torch.Tensor,
                progress: Progress = Progress(),
                present: torch.Tensor | None = None) -> Segmentation:
        b, e, t, _ = h_fwd.shape
        # fp32 under autocast: the logits feed KL terms and a threshold
        q = self.posterior(torch.cat([h_fwd, h_rev], -1)).squeeze(-1).float()  # [B, E, T]
        p = self.prior_logits(h_fwd)
        if self.training and self.sample:
            u = torch.rand_like(q).clamp(1e-6, 1 - 1e-6)
            q_noisy = q + u.log() - (-u).log1p()  # + logistic noise: the relaxed Bernoulli
        else:
            q_noisy = q
        soft = torch.sigmoid(q_noisy / self.temperature)
        gate = (soft > 0.5).float() + soft - soft.detach()
        fixed, value = self.forced(t, h_fwd.device, present)
        gate = torch.where(fixed, value.float(), gate)
        kl = ((1 - self.rate_mix) * bernoulli_kl(q, p)
              + self.rate_mix * bernoulli_kl(q, q.new_full((), self.rate_logit)))
        steps = e * t if present is None else present.flatten(1).sum(1).clamp_min(1)
        kl = (kl * ~fixed).flatten(1).sum(1) / steps
        start = torch.arange(t, device=h_fwd.device).expand(b, e, t)
        return Segmentation(start, gate.detach() > 0.5, hold_assignment(gate), kl, weight=gate,
                            fixed=fixed)
