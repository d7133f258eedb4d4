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
- every candidate start's end categorical is computed at once and the chain of segments from step 0 followed by
  pointer jumping: the same cut as drawing segment after segment, in a fixed number of steps (no host
  synchronisation, one CUDA graph);
- the edge type is read at the segment's start and held (``model.net.posterior_readout: start``); forecasting
  runs the prior's hazard through the online state machine.

Shapes: B batch, E edges, T transitions, R LSTM width, H hidden width, S = T slots (slot s starts at step s).
"""

from __future__ import annotations

import math

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
        # The cut's computation: every candidate start at once (True: no host synchronisation, the form a CUDA graph
        # captures), segment after segment (False: T times less work, the CPU's choice); None picks by device. Both
        # give the same cut and gradients (tests/test_segment_end.py).
        self.sync_free: bool | None = None
        # f_q = v . ELU(W_at a_t + W_start [h_fwd_s, h_rev_s]) + c. a_t: the candidate's features [h_fwd_t, h_rev_t]
        # (reads=position, once per clip) or its offset t - s (reads=remaining: SKID reads the remaining trajectory
        # at the segment's start only)
        self.at = nn.Linear(2 * rnn_hidden, hidden) if reads == "position" else SumLinear(len(OFFSET_SCALES), hidden)
        self.start = nn.Linear(2 * rnn_hidden, hidden, bias=False)
        self.out = SumLinear(hidden, 1)
        with torch.no_grad():  # start at the prior's rate: segments of about 1 / rate steps
            self.out.bias.fill_(self.rate_logit)

    def candidates(self, feats: torch.Tensor) -> torch.Tensor:
        """What the posterior hazard reads of each candidate end, once per clip: W_at applied to the features there,
        [B, E, T, H] (reads=position), or W_at's value at each offset 0..T-1 from a start, [T, H] (reads=remaining)."""
        if self.reads == "position":
            return self.at(feats)
        return self.at(offset_features(torch.arange(feats.shape[2], device=feats.device)))

    def posterior_logits(self, feats: torch.Tensor, at: torch.Tensor, start: torch.Tensor | None = None
                         ) -> torch.Tensor:
        """The posterior hazard's logits: feats [B, E, T, 2R] (the features [h_fwd, h_rev] at each step), ``at`` of
        :meth:`candidates` and the segments' starts [B, E] long -> [B, E, T], the hazard at each step t of the
        segment that started there; without ``start``, of every candidate start at once -> [B, E, S=T, T] (entry
        (s, t); only t > s is read)."""
        t = feats.shape[2]
        step = torch.arange(t, device=feats.device)
        if start is None:
            s, offset = self.start(feats).unsqueeze(3), step.view(1, -1) - step.view(-1, 1)  # [B, E, S, 1, H]
            at = at.unsqueeze(2) if self.reads == "position" else at  # [B, E, 1, T, H]
        else:
            index = start.clamp(max=t - 1)[..., None, None].expand(-1, -1, 1, feats.shape[-1])
            s, offset = self.start(feats.gather(2, index)), step - start.unsqueeze(-1)  # [B, E, 1, H]; [B, E, T]
        if self.reads == "remaining":  # SKID: the candidate's offset from the start, read from the table
            at = at[offset.clamp_min(0)]
        return self.out(F.elu(at + s)).squeeze(-1).float()

    def gumbel(self, log_q: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
        """Gumbel noise for the end draws of the segments starting at ``start`` (log_q [..., T+1])."""
        return -torch.empty_like(log_q).exponential_().log()

    def read_end(self, log_q: torch.Tensor) -> torch.Tensor:
        """The end evaluation reads from each segment's end categorical [..., T+1] -> [...] long."""
        return median_end(log_q)

    def _draw(self, log_q: torch.Tensor, start: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Each segment's end from its categorical log_q [..., T+1] (start [...] long): drawn in training with a
        straight-through Gumbel-softmax, read (:meth:`read_end`) in evaluation -> the end [...] long and its
        straight-through one-hot [..., T+1] (exactly one-hot forward, the soft sample's gradient)."""
        t = log_q.shape[-1] - 1
        if self.training:
            # exp(z - logsumexp z), not F.softmax: ATen's softmax over a long row rounds with the CPU's vector
            # width, and a last bit here can flip a drawn end (docs/reliability.md)
            z = (log_q + self.gumbel(log_q, start)) / self.temperature
            soft = (z - z.logsumexp(-1, keepdim=True)).exp()
            end = soft.argmax(-1)
        else:
            soft, end = None, self.read_end(log_q)
        # a segment ends after its start, whatever the numbers (NaN hazards would otherwise hold it there)
        end = torch.maximum(end, start + 1).clamp(max=t)
        one_hot = (end.unsqueeze(-1) == torch.arange(t + 1, device=end.device)).to(log_q.dtype)  # not F.one_hot:
        # its range check synchronises with the host
        drawn = one_hot if soft is None or not torch.is_grad_enabled() else one_hot + soft - soft.detach()
        return end, drawn

    def _kl(self, log_q: torch.Tensor, p: torch.Tensor, start: torch.Tensor, fixed: torch.Tensor,
            value: torch.Tensor) -> torch.Tensor:
        """The duration KL of each segment: its end categorical log_q [..., T+1] against the learned prior hazard p
        and the fixed rate, mixed by ``rate_mix`` -> [...]."""
        learned = end_log_probs(p, start, fixed, value)
        rate = end_log_probs(torch.full_like(p, self.rate_logit), start, fixed, value)
        return (1 - self.rate_mix) * end_kl(log_q, learned) + self.rate_mix * end_kl(log_q, rate)

    def segment(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, x: torch.Tensor,
                progress: Progress = Progress(), present: torch.Tensor | None = None) -> Segmentation:
        b, e, t, _ = h_fwd.shape
        fixed, value = self.forced(t, h_fwd.device, present)
        fixed, value = fixed.expand(b, e, t), value.expand(b, e, t)
        feats = torch.cat([h_fwd, h_rev], -1)
        p = self.prior_logits(h_fwd)
        every_start = h_fwd.is_cuda if self.sync_free is None else self.sync_free
        cut = self._every_start if every_start else self._segment_by_segment
        ends, kl = cut(feats, p, fixed, value)
        gate = torch.where(fixed, value.to(ends.dtype), ends[..., :t])  # step 0 is fixed: the first segment's start
        steps = e * t if present is None else present.flatten(1).sum(1).clamp_min(1)
        slots = torch.arange(t, device=h_fwd.device).expand(b, e, t)
        valid = gate.detach() > 0.5
        return Segmentation(slots, valid, hold_assignment(gate), kl.sum(1) / steps, weight=gate, fixed=fixed)

    def _every_start(self, feats: torch.Tensor, p: torch.Tensor, fixed: torch.Tensor, value: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
        """The cut with every candidate start's end categorical at once ([B, E, S, T+1]: given the features, the
        ends of different starts are independent), one end drawn (or read) per start, and the chain of segments
        from step 0 found by pointer jumping (log2 T gathers): a fixed number of operations, no host
        synchronisation. -> the chain's drawn ends [B, E, T+1] (straight-through) and its duration KL [B, E]."""
        t = feats.shape[2]
        starts = torch.arange(t, device=feats.device)
        at_start, fixed_s, value_s = starts.view(1, 1, t), fixed.unsqueeze(2), value.unsqueeze(2)
        log_q = end_log_probs(self.posterior_logits(feats, self.candidates(feats)), at_start, fixed_s,
                              value_s)  # [B, E, S, T+1]
        seg_kl = self._kl(log_q, p.unsqueeze(2), at_start, fixed_s, value_s)  # the prior reads no start
        end, drawn = self._draw(log_q, starts.expand(*log_q.shape[:-1]))
        on = chain_from_zero(end).to(log_q.dtype)  # [B, E, S]: the starts of the segments from step 0
        ends = (on.unsqueeze(-1) * drawn).sum(2)  # the chain's drawn ends (fp32, not a matmul under autocast)
        # a segment exists (weight 1 forward) where the previous one's drawn end opens it: the straight-through value
        # of that end; 1 at a fixed boundary and for the first segment
        opens = drawn.gather(-1, end.unsqueeze(-1)).squeeze(-1)
        opens = torch.where(F.pad(fixed, (0, 1), value=True).gather(-1, end), 1.0, opens)
        exists = torch.where(starts == 0, 1.0, torch.zeros_like(ends).scatter_add(-1, end, opens * on)[..., :t])
        return ends, (seg_kl * exists * on).sum(-1)

    def _segment_by_segment(self, feats: torch.Tensor, p: torch.Tensor, fixed: torch.Tensor, value: torch.Tensor
                            ) -> tuple[torch.Tensor, torch.Tensor]:
        """The same cut drawn segment after segment (one pass per segment, vectorised over batch and edges, at most
        T passes whatever the numbers): on a CPU cheaper than every start at once (a pass costs a T-th of it),
        but each pass asks the host whether an edge still runs."""
        b, e, t, _ = feats.shape
        start = torch.zeros(b, e, dtype=torch.long, device=feats.device)
        exists = torch.ones(b, e, device=feats.device)  # segment k's straight-through existence
        ends = feats.new_zeros(b, e, t + 1, dtype=torch.float32)  # the drawn ends, summed over segments
        kl = feats.new_zeros(b, e, dtype=torch.float32)
        running = torch.ones(b, e, dtype=torch.bool, device=feats.device)
        at = self.candidates(feats)
        for _ in range(t):
            if not bool(running.any()):
                break
            log_q = end_log_probs(self.posterior_logits(feats, at, start), start, fixed, value)
            kl = kl + self._kl(log_q, p, start, fixed, value) * exists * running
            end, drawn = self._draw(log_q, start)
            ends = ends + drawn * running.unsqueeze(-1)
            # the next segment's existence: forced where the end is a fixed boundary, else the drawn end's
            opens = drawn.gather(-1, end.unsqueeze(-1)).squeeze(-1)
            at_fixed = F.pad(fixed, (0, 1), value=True).gather(-1, end.unsqueeze(-1)).squeeze(-1)
            exists = torch.where(running, torch.where(at_fixed, 1.0, opens), exists)
            start = torch.where(running, end, start)
            running = start < t
        return ends, kl


def chain_from_zero(end: torch.Tensor) -> torch.Tensor:
    """The segments that follow each other from step 0: end [..., S] long, the end of a segment starting at each
    step s (in (s, S]; S: the clip's end) -> [..., S] bool, whether s starts one of them. Pointer jumping: after
    round j the starts reached in fewer than 2^j segments are known, and the pointers jump 2^j segments; ceil(log2
    (S + 1)) rounds of a scatter and a gather, whatever the ends."""
    size = end.shape[-1]
    jump = torch.cat([end, torch.full_like(end[..., :1], size)], -1)  # [..., S+1]; the clip's end absorbs
    reached = torch.zeros_like(jump, dtype=torch.long)
    reached[..., 0] = 1
    for _ in range(max(1, math.ceil(math.log2(size + 1)))):
        reached = reached | torch.zeros_like(reached).scatter_add(-1, jump, reached).clamp(max=1)
        jump = jump.gather(-1, jump)
    return reached[..., :size].bool()
