"""DIDER's duration latent as each segment's end: a categorical over where the segment ends, scored at every
candidate end from the features there.

The paper draws one duration latent per segment; so does this plugin, but the latent is the segment's end
position e_k (its length d_k = e_k - s_k), not a Gaussian fraction of the remaining steps read at the
segment's start. That fraction gets no signal about where a segment should end (a duration read at the start
must predict the end from there, and pushed through the fraction map its prior is cheapest at one step), so
the learned slots collapse to one step; scoring each candidate end where it would be, as every working
segment model does, lets boundaries sit where the interaction changes.

For an edge's segment k starting at s_k:
- posterior: a hazard at each later step t, sigmoid(f_q(h_fwd_t, h_rev_t, h_fwd_s, h_rev_s)): the features
  at t (the past and the remaining trajectory) against those at the segment's start. The end's categorical is
  q(e) = h_e prod_{s<t<e} (1 - h_t) over s < e < L, and the rest of the mass at L, the next fixed boundary
  (where an edge enters, where the forecast starts, or the clip's end: "runs to the end");
- prior: the past-only hazard of :class:`~dider.models.hazard.HazardPrior` in the same form, mixed with a fixed
  boundary rate: per segment, KL(q_k || p_k) is exact (a sum over the candidate ends);
- training draws e_k with a straight-through Gumbel-softmax over the candidate ends (exactly one end forward,
  the soft sample's gradient to every candidate); the soft sample enters the held assignment at every
  candidate, so each candidate end gets the gradient of switching the held type there;
- segment k + 1 exists where segment k ends before the clip's end: its edge KL and duration KL are weighted by
  that straight-through indicator, so the number of segments has a gradient;
- evaluation takes each segment's median end (the first e with q(end <= e) >= 1/2);
- the edge type is read at the segment's start and held (``model.net.posterior_readout: start``); forecasting
  runs the prior's hazard through the online state machine.

Shapes: B batch, E edges, T transitions, R LSTM width, H hidden width, S = T slots (slot s starts at step s).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from dider.models.hazard import HazardPrior, hold_assignment
from dider.models.layers import SumLinear
from dider.models.plugins import Progress
from dider.models.segments import Segmentation
from dider.validation import above, check_settings, one_of

# A log-probability that is 0 in fp32 after exp (finite, so 0 * (log q - log p) stays 0 with its gradient).
IMPOSSIBLE = -1e4


# Offsets (in steps) around which a candidate end's offset from its segment's start is encoded (reads=remaining).
OFFSET_SCALES = (1, 2, 4, 8, 16, 32, 64)


def offset_features(offset: torch.Tensor) -> torch.Tensor:
    """[...] steps >= 0 -> [..., len(OFFSET_SCALES)]: Gaussian bumps on log(1 + offset) at each scale."""
    centres = torch.tensor(OFFSET_SCALES, device=offset.device, dtype=torch.float32).log1p()
    return torch.exp(-2.0 * (offset.float().log1p().unsqueeze(-1) - centres) ** 2)


def end_log_probs(logits: torch.Tensor, start: torch.Tensor, fixed: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """The categorical over a segment's end given hazards at every step.

    logits [B, E, T]: each step's hazard (a boundary there, given none since the start); start [B, E] long;
    fixed, value [B, E, T] bool: steps whose boundary is fixed, and whether it is a boundary. -> [B, E, T+1]
    log q(e): e in (start, L], L the first fixed boundary after the start or T (the clip's end), the mass not
    ended before L put on L; IMPOSSIBLE elsewhere."""
    t = logits.shape[-1]
    after = torch.arange(t, device=logits.device) > start.unsqueeze(-1)
    log_h = torch.where(fixed, torch.where(value, 0.0, IMPOSSIBLE), F.logsigmoid(logits))
    log_stay = torch.where(fixed, torch.where(value, IMPOSSIBLE, 0.0), F.logsigmoid(-logits))
    log_stay = torch.where(after, log_stay, 0.0)
    survive = log_stay.cumsum(-1)  # log P(no boundary in (start, t])
    before = F.pad(survive[..., :-1], (1, 0))  # log P(no boundary in (start, t)), exact (no subtraction)
    log_q = torch.where(after, log_h + before, IMPOSSIBLE)
    return torch.cat([log_q, survive[..., -1:]], -1).clamp_min(IMPOSSIBLE)


def median_end(log_q: torch.Tensor) -> torch.Tensor:
    """[B, E, T+1] log q(e) -> [B, E] long: the first e with q(end <= e) >= 1/2."""
    return (log_q.exp().cumsum(-1) >= 0.5 - 1e-6).to(torch.uint8).argmax(-1)


def end_kl(log_q: torch.Tensor, log_p: torch.Tensor) -> torch.Tensor:
    """KL(q || p) of two end categoricals [B, E, T+1] (log-probabilities) -> [B, E]."""
    return (log_q.exp() * (log_q - log_p)).sum(-1)


class SegmentEnd(HazardPrior):
    """One latent per segment, its end, scored at each candidate end (see the module docstring).

    ``temperature``: of the Gumbel-softmax over the candidate ends. ``reads``: ``position`` (DIDER) or
    ``remaining`` (SKID). ``rate``, ``rate_mix``, ``online_threshold`` and ``burn_in``:
    :class:`~dider.models.hazard.HazardPrior` (the fixed ``rate``, mixed into the prior, is what a boundary costs).
    """

    SETTINGS = HazardPrior.SETTINGS | {"temperature": above(0), "reads": one_of("position", "remaining")}

    def __init__(
        self,
        rnn_hidden: int = 64,
        hidden: int = 64,
        rate: float = 0.02,
        rate_mix: float = 0.5,
        temperature: float = 0.5,
        online_threshold: float = 0.5,
        burn_in: int | None = None,
        reads: str = "position",
    ) -> None:
        check_settings(self, locals())
        super().__init__(rnn_hidden, hidden, rate, rate_mix, online_threshold, burn_in)
        self.temperature = temperature
        # Online, a segment also ends where the prior reads another type than the one held: the prior hazard is
        # trained to foresee where the posterior ends a segment, which the past rarely can, so on its own it
        # seldom fires (:meth:`RelationalVAE.advance_edges`).
        self.online_retype = True
        self.reads = reads
        # f_q = v . ELU(W_at a_t + W_start [h_fwd_s, h_rev_s]) + c. a_t: the candidate's features [h_fwd_t, h_rev_t]
        # (reads=position, once per clip) or its offset t - s (reads=remaining: SKID reads the remaining trajectory
        # at the segment's start only)
        self.at = nn.Linear(2 * rnn_hidden, hidden) if reads == "position" else SumLinear(len(OFFSET_SCALES), hidden)
        self.start = nn.Linear(2 * rnn_hidden, hidden, bias=False)
        self.out = SumLinear(hidden, 1)
        with torch.no_grad():  # start at the prior's rate: segments of about 1 / rate steps
            self.out.bias.fill_(self.rate_logit)

    def posterior_logits(self, at: torch.Tensor, feats: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
        """The posterior hazard's logits [B, E, T] for segments starting at ``start`` [B, E] long, given the
        features [B, E, T, 2R] and ``at``: W_at features [B, E, T, H] (reads=position) or W_at's value at each
        offset from a start, [T, H] (reads=remaining)."""
        t = feats.shape[2]
        index = start.clamp(max=t - 1)[..., None, None].expand(-1, -1, 1, feats.shape[-1])
        s = self.start(feats.gather(2, index))  # [B, E, 1, H]
        if self.reads == "remaining":  # the candidate's offset from the start, read from the table
            at = at[(torch.arange(t, device=feats.device) - start.unsqueeze(-1)).clamp_min(0)]  # [B, E, T, H]
        return self.out(F.elu(at + s)).squeeze(-1).float()

    def segment(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, x: torch.Tensor,
                progress: Progress = Progress(), present: torch.Tensor | None = None) -> Segmentation:
        b, e, t, _ = h_fwd.shape
        feats = torch.cat([h_fwd, h_rev], -1)
        if self.reads == "position":
            at = self.at(feats)
        else:  # W_at at each integer offset, once per clip; each segment's pass reads it by index
            at = self.at(offset_features(torch.arange(t, device=h_fwd.device)))  # [T, H]
        p = self.prior_logits(h_fwd)
        rate = torch.full_like(p, self.rate_logit)
        fixed, value = self.forced(t, h_fwd.device, present)
        fixed, value = fixed.expand(b, e, t), value.expand(b, e, t)
        draw = self.training
        start = torch.zeros(b, e, dtype=torch.long, device=h_fwd.device)
        exists = torch.ones(b, e, device=h_fwd.device)  # segment k's straight-through existence
        ends = h_fwd.new_zeros(b, e, t + 1, dtype=torch.float32)  # the drawn ends, summed over segments
        kl = h_fwd.new_zeros(b, e, dtype=torch.float32)
        running = torch.ones(b, e, dtype=torch.bool, device=h_fwd.device)
        for _ in range(t):  # one pass per segment, vectorised over batch and edges; each pass moves every start on
            if not bool(running.any()):
                break
            log_q = end_log_probs(self.posterior_logits(at, feats, start), start, fixed, value)
            seg_kl = ((1 - self.rate_mix) * end_kl(log_q, end_log_probs(p, start, fixed, value))
                      + self.rate_mix * end_kl(log_q, end_log_probs(rate, start, fixed, value)))
            kl = kl + seg_kl * exists * running
            if draw:
                gumbel = -torch.empty_like(log_q).exponential_().log()
                # exp(z - logsumexp z), not F.softmax: ATen's softmax over a long row rounds with the CPU's vector
                # width, and a last bit here can flip a drawn end (docs/reliability.md)
                z = (log_q + gumbel) / self.temperature
                soft = (z - z.logsumexp(-1, keepdim=True)).exp()
                end = soft.argmax(-1)
            else:
                soft, end = None, median_end(log_q)
            # a segment ends after its start, whatever the numbers (NaN hazards would otherwise hold it there)
            end = torch.maximum(end, start + 1).clamp(max=t)
            one_hot = F.one_hot(end, t + 1).to(log_q.dtype)
            drawn = one_hot if soft is None or not torch.is_grad_enabled() else one_hot + soft - soft.detach()
            ends = ends + drawn * running.unsqueeze(-1)
            # the next segment's existence: forced where the end is a fixed boundary, else the drawn end's
            ended_free = drawn.gather(-1, end.unsqueeze(-1)).squeeze(-1)
            at_fixed = F.pad(fixed, (0, 1), value=True).gather(-1, end.unsqueeze(-1)).squeeze(-1)
            exists = torch.where(running, torch.where(at_fixed, 1.0, ended_free), exists)
            start = torch.where(running, end, start)
            running = start < t
        gate = torch.where(fixed, value.float(), ends[..., :t])  # step 0 is fixed: the first segment's start
        steps = e * t if present is None else present.flatten(1).sum(1).clamp_min(1)
        slots = torch.arange(t, device=h_fwd.device).expand(b, e, t)
        valid = gate.detach() > 0.5
        return Segmentation(slots, valid, hold_assignment(gate), kl.sum(1) / steps, weight=gate, fixed=fixed)
