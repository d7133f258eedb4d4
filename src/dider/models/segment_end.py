"""DIDER's duration latent as each segment's end: a categorical over where the segment ends, scored
at every candidate end from the features there.

The paper draws one duration latent per segment; so does this plugin, but the latent is the
segment's end position e_k (its length d_k = e_k - s_k), not a Gaussian fraction of the remaining
steps read at the segment's start. That fraction gets no signal about where a segment should end (a
duration read at the start must predict the end from there, and pushed through the fraction map its
prior is cheapest at one step), so the learned slots collapse to one step; scoring each candidate
end where it would be, as every working segment model does, lets boundaries sit where the
interaction changes.

For an edge's segment k starting at s_k, holding type z_k:
- posterior: a hazard at each later step t, sigmoid(f_q(h_fwd_t, h_rev_t, h_fwd_s, h_rev_s)): the
  features at t (the past and the remaining trajectory) against those at the segment's start. The
  end's categorical is q(e) = h_e prod_{s<t<e} (1 - h_t) over s < e < L, and the rest of the mass at
  L, the next fixed boundary (where an edge enters, where the forecast starts, or the clip's end:
  "runs to the end");
- prior: a past-only hazard in the same form (:class:`~dider.models.held_hazard.HeldHazard`): with
  ``online_prior: held_type`` it reads the type the segment holds and its age besides the past,
  p(end at t | z_k, t - s_k, h_fwd_t); mixed with a fixed boundary ``rate``, what a boundary costs.
  The duration KL of a segment is E_{q(z_k)} KL(q(e_k) || p(e_k | z_k)), exact (a sum over the
  candidate ends and types), q(z_k) the posterior's type at the segment's start;
- training draws e_k with a straight-through Gumbel-softmax over the candidate ends (exactly one end
  forward, the soft sample's gradient to every candidate); the soft sample enters the held
  assignment at every candidate, so each candidate end gets the gradient of switching the held type
  there;
- segment k + 1 exists where segment k ends before the clip's end: its edge KL and duration KL are
  weighted by that straight-through indicator, so the number of segments has a gradient;
- evaluation reads each segment's end where it is decided (``end_readout: threshold``: the first
  candidate whose posterior hazard passes 1/2), or at the median of q(end) (``median``);
  ``held_mode`` (the default) reads the decided end too, but a segment holding an interaction (a
  type other than 0, "none") that no candidate ends takes q(end)'s mode instead of running to the
  next fixed boundary: a push the hazard never closes would otherwise hold its interaction to the
  clip's end, while a "none" segment with no decided end rightly runs on;
- every candidate start's end categorical is computed at once and the chain of segments from step 0
  followed by pointer jumping: the same cut as drawing segment after segment, in a fixed number of
  steps (no host synchronisation, one CUDA graph);
- the edge type is read at the segment's start and held (``model.net.posterior_readout: start``);
  online, a segment ends where the prior hazard passes ``online_threshold`` and the next type is the
  prior's, the held type excluded (:meth:`RelationalVAE.advance_edges`). The prior hazard is also
  fitted at every step to where the posterior's held type changes (:meth:`boundary_fit`, the
  objective's ``boundary_fit`` term).

Shapes: B batch, E edges, T transitions, R LSTM width, H hidden width, K edge types, S = T slots
(slot s starts at step s).
"""

from __future__ import annotations

from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import nn

from dider.models.end_categorical import (
    OFFSET_SCALES,
    chain_from_zero,
    decided_end,
    end_kl,
    end_log_probs,
    median_end,
    offset_features,
)
from dider.models.hazard import HazardPrior, fires, hold_assignment
from dider.models.held_hazard import HeldHazard
from dider.models.layers import SumLinear
from dider.models.plugins import Progress
from dider.models.segments import Segmentation
from dider.validation import above, check_settings, integer, one_of


class SegmentEnd(HazardPrior):
    """One latent per segment, its end, scored at each candidate end (see the module docstring).

    ``temperature``: of the Gumbel-softmax over the candidate ends. ``reads``: ``position`` (DIDER)
    or ``remaining`` (SKID). ``end_readout``: where evaluation reads a segment's end, ``threshold``
    (where its hazard passes 1/2), ``held_mode`` (the threshold's end, or q(end)'s mode for a
    segment holding an interaction that no candidate ends) or ``median``. ``online_prior``: the
    prior hazard reads the held type and the segment's age besides the past (``held_type``) or the
    past alone (``past``; online, a segment then also ends where the prior's type flips).
    ``num_types``: the edge types (the held type's outputs). ``rate``, ``rate_mix``,
    ``online_threshold`` and ``burn_in``: :class:`~dider.models.hazard.HazardPrior` (the fixed
    ``rate``, mixed into the prior, is what a boundary costs).
    """

    SETTINGS = HazardPrior.SETTINGS | {
        "temperature": above(0), "reads": one_of("position", "remaining"),
        "end_readout": one_of("held_mode", "threshold", "median"),
        # >= 2: the network's num_edges says
        "online_prior": one_of("held_type", "past"), "num_types": integer(1),
    }
    # non-integer settings that fix parameter shapes
    SHAPES: ClassVar[tuple[str, ...]] = ("reads", "online_prior")

    def __init__(
        self,
        rnn_hidden: int = 64,
        hidden: int = 64,
        rate: float = 0.05,
        rate_mix: float = 0.5,
        temperature: float = 0.5,
        online_threshold: float = 0.5,
        burn_in: int | None = None,
        reads: str = "position",
        end_readout: str = "held_mode",
        online_prior: str = "held_type",
        num_types: int = 2,
    ) -> None:
        check_settings(self, locals())
        super().__init__(rnn_hidden, hidden, rate, rate_mix, online_threshold, burn_in)
        self.temperature, self.reads, self.end_readout = temperature, reads, end_readout
        self.prior = HeldHazard(rnn_hidden, hidden, num_types, online_prior == "held_type",
                                self.rate_logit)
        # Online, a segment also ends where the prior's type head reads another type than the one
        # held: an onset is rare and its step uncertain, so even a hazard that ranks onsets well
        # (the held type's: AUC 0.92 on the synthetic set) seldom passes 1/2 at one; the head's flip
        # finds five times the onsets and forecasts better (docs/models.md).
        self.online_retype = True
        # online, a boundary brings another type (runs of one type)
        self.excludes_held = online_prior == "held_type"
        # The cut's computation: every candidate start at once (True: no host synchronisation, the
        # form a CUDA graph captures), segment after segment (False: T times less work, the CPU's
        # choice); None picks by device. Both give the same cut and gradients
        # (tests/test_segment_end.py).
        self.sync_free: bool | None = None
        # f_q = v . ELU(W_at a_t + W_start [h_fwd_s, h_rev_s]) + c. a_t: the candidate's features
        # [h_fwd_t, h_rev_t] (reads=position, once per clip) or its offset t - s (reads=remaining:
        # SKID reads the remaining trajectory at the segment's start only)
        self.at = (nn.Linear(2 * rnn_hidden, hidden) if reads == "position"
                   else SumLinear(len(OFFSET_SCALES), hidden))
        self.start = nn.Linear(2 * rnn_hidden, hidden, bias=False)
        self.out = SumLinear(hidden, 1)
        with torch.no_grad():  # start at the prior's rate: segments of about 1 / rate steps
            self.out.bias.fill_(self.rate_logit)

    def prior_logits(self, h_fwd: torch.Tensor) -> torch.Tensor:
        """The prior hazard's logits at every step, the held type unknown: [..., R] -> [...] (its
        mean over types)."""
        return self.prior.steps(h_fwd).mean(-1)

    def candidates(self, feats: torch.Tensor) -> torch.Tensor:
        """What the posterior hazard reads of each candidate end, once per clip: W_at applied to the
        features there, [B, E, T, H] (reads=position), or W_at's value at each offset 0..T-1 from a
        start, [T, H] (reads=remaining)."""
        if self.reads == "position":
            return self.at(feats)
        return self.at(offset_features(torch.arange(feats.shape[2], device=feats.device)))

    def posterior_logits(self, feats: torch.Tensor, at: torch.Tensor,
                         start: torch.Tensor | None = None
                         ) -> torch.Tensor:
        """The posterior hazard's logits: feats [B, E, T, 2R] (the features [h_fwd, h_rev] at each
        step), ``at`` of :meth:`candidates` and the segments' starts [B, E] long -> [B, E, T], the
        hazard at each step t of the segment that started there; without ``start``, of every
        candidate start at once -> [B, E, S=T, T] (entry (s, t); only t > s is read)."""
        t = feats.shape[2]
        step = torch.arange(t, device=feats.device)
        if start is None:
            # [B, E, S, 1, H]
            s, offset = self.start(feats).unsqueeze(3), step.view(1, -1) - step.view(-1, 1)
            at = at.unsqueeze(2) if self.reads == "position" else at  # [B, E, 1, T, H]
        else:
            index = start.clamp(max=t - 1)[..., None, None].expand(-1, -1, 1, feats.shape[-1])
            # [B, E, 1, H]; [B, E, T]
            s, offset = self.start(feats.gather(2, index)), step - start.unsqueeze(-1)
        # SKID: the candidate's offset from the start, read from the table
        if self.reads == "remaining":
            at = at[offset.clamp_min(0)]
        return self.out(F.elu(at + s)).squeeze(-1).float()

    def gumbel(self, log_q: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
        """Gumbel noise for the end draws of the segments starting at ``start`` (log_q [...,
        T+1])."""
        return -torch.empty_like(log_q).exponential_().log()

    def _draw(self, log_q: torch.Tensor, logits: torch.Tensor, start: torch.Tensor,
              fixed: torch.Tensor, value: torch.Tensor,
              interaction: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Each segment's end from its categorical log_q [..., T+1] (its hazards' logits [..., T],
        start [...] long): drawn in training with a straight-through Gumbel-softmax, read in
        evaluation (``end_readout``; ``interaction`` [...] bool: whether the segment holds an
        interaction, None: not known) -> the end [...] long and its straight-through one-hot [...,
        T+1] (exactly one-hot forward, the soft sample's gradient)."""
        t = log_q.shape[-1] - 1
        if self.training:
            # exp(z - logsumexp z), not F.softmax: ATen's softmax over a long row rounds with the
            # CPU's vector width, and a last bit here can flip a drawn end (docs/reliability.md)
            z = (log_q + self.gumbel(log_q, start)) / self.temperature
            soft = (z - z.logsumexp(-1, keepdim=True)).exp()
            end = soft.argmax(-1)
        elif self.end_readout != "median":
            soft, end = None, decided_end(logits, start, fixed, value)
            # held_mode: an interaction no candidate ends stops at q(end)'s mode
            if interaction is not None:
                end = torch.where((end >= t) & interaction, log_q.argmax(-1), end)
        else:
            soft, end = None, median_end(log_q)
        # a segment ends after its start, whatever the numbers (NaN hazards would otherwise hold it
        # there)
        end = torch.maximum(end, start + 1).clamp(max=t)
        # not F.one_hot: its range check synchronises with the host
        one_hot = (end.unsqueeze(-1) == torch.arange(t + 1, device=end.device)).to(log_q.dtype)
        drawn = (one_hot if soft is None or not torch.is_grad_enabled()
                 else one_hot + soft - soft.detach())
        return end, drawn

    def _kl(self, log_q: torch.Tensor, prior: torch.Tensor, types: torch.Tensor,
            start: torch.Tensor, fixed: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
        """The duration KL of each segment: its end categorical log_q [..., T+1] against the prior's
        for each held type (prior [..., K', T] logits), weighted by the segment's type probabilities
        ``types`` [..., K'], mixed with the fixed rate's by ``rate_mix`` -> [...]. start, fixed,
        value broadcast against log_q's leading dims."""
        k_start, k_fixed, k_value = start.unsqueeze(-1), fixed.unsqueeze(-2), value.unsqueeze(-2)
        # [..., K']
        learned = end_kl(log_q.unsqueeze(-2), end_log_probs(prior, k_start, k_fixed, k_value))
        rate = end_log_probs(torch.full_like(prior[..., 0, :], self.rate_logit), start, fixed,
                             value)
        return (1 - self.rate_mix) * (types * learned).sum(-1) + self.rate_mix * end_kl(log_q, rate)

    def segment(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, x: torch.Tensor,
                progress: Progress = Progress(), present: torch.Tensor | None = None,
                types: torch.Tensor | None = None) -> Segmentation:
        """types: [B, E, T, K] the posterior's type probabilities at each step (a segment's type is
        read at its start), which the held type's prior reads and the ``held_mode`` readout asks;
        None: every type alike."""
        b, e, t, _ = h_fwd.shape
        fixed, value = self.forced(t, h_fwd.device, present)
        fixed, value = fixed.expand(b, e, t), value.expand(b, e, t)
        feats = torch.cat([h_fwd, h_rev], -1)
        steps, width = self.prior.steps(h_fwd), self.prior.width  # [B, E, T, K']
        # [B, E, T] bool or None: evaluation's end readout asks it
        interaction = self._holds_interaction(types)
        if not self.prior.held or types is None:
            types = steps.new_full((b, e, t, width), 1.0 / width)
        every_start = h_fwd.is_cuda if self.sync_free is None else self.sync_free
        cut = self._every_start if every_start else self._segment_by_segment
        ends, kl = cut(feats, steps, types.float(), fixed, value, interaction)
        # step 0 is fixed: the first segment's start
        gate = torch.where(fixed, value.to(ends.dtype), ends[..., :t])
        n = e * t if present is None else present.flatten(1).sum(1).clamp_min(1)
        slots = torch.arange(t, device=h_fwd.device).expand(b, e, t)
        valid = gate.detach() > 0.5
        return Segmentation(slots, valid, hold_assignment(gate), kl.sum(1) / n, weight=gate,
                            fixed=fixed)

    def _holds_interaction(self, types: torch.Tensor | None) -> torch.Tensor | None:
        """Whether the segment starting at each step holds an interaction, where evaluation's end
        readout needs it: types [B, E, T, K] (the posterior's, read at the start) -> [B, E, T] bool,
        or None (not needed, or no types given: every end read by the threshold)."""
        if self.training or self.end_readout != "held_mode" or types is None:
            return None
        return types[..., 1:].float().sum(-1) > 0.5

    def _every_start(self, feats: torch.Tensor, steps: torch.Tensor, types: torch.Tensor,
                     fixed: torch.Tensor,
                     value: torch.Tensor, interaction: torch.Tensor | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor]:
        """The cut with every candidate start's end categorical at once ([B, E, S, T+1]: given the
        features, the ends of different starts are independent), one end drawn (or read) per start,
        and the chain of segments from step 0 found by pointer jumping (log2 T gathers): a fixed
        number of operations, no host synchronisation. -> the chain's drawn ends [B, E, T+1]
        (straight-through) and its duration KL [B, E]."""
        t = feats.shape[2]
        starts = torch.arange(t, device=feats.device)
        at_start, fixed_s, value_s = starts.view(1, 1, t), fixed.unsqueeze(2), value.unsqueeze(2)
        logits = self.posterior_logits(feats, self.candidates(feats))  # [B, E, S, T]
        log_q = end_log_probs(logits, at_start, fixed_s, value_s)  # [B, E, S, T+1]
        seg_kl = self._kl(log_q, self.prior.of_start(steps, starts), types, at_start, fixed_s,
                          value_s)
        end, drawn = self._draw(log_q, logits, starts.expand(*log_q.shape[:-1]), fixed_s, value_s,
                                interaction)
        # [B, E, S]: the starts of the segments from step 0
        on = chain_from_zero(end).to(log_q.dtype)
        # the chain's drawn ends (fp32, not a matmul under autocast)
        ends = (on.unsqueeze(-1) * drawn).sum(2)
        # a segment exists (weight 1 forward) where the previous one's drawn end opens it: the
        # straight-through value of that end; 1 at a fixed boundary and for the first segment
        opens = drawn.gather(-1, end.unsqueeze(-1)).squeeze(-1)
        opens = torch.where(F.pad(fixed, (0, 1), value=True).gather(-1, end), 1.0, opens)
        exists = torch.where(starts == 0, 1.0,
                             torch.zeros_like(ends).scatter_add(-1, end, opens * on)[..., :t])
        return ends, (seg_kl * exists * on).sum(-1)

    def _segment_by_segment(self, feats: torch.Tensor, steps: torch.Tensor, types: torch.Tensor,
                            fixed: torch.Tensor, value: torch.Tensor,
                            interaction: torch.Tensor | None = None
                            ) -> tuple[torch.Tensor, torch.Tensor]:
        """The same cut drawn segment after segment (one pass per segment, vectorised over batch and
        edges, at most T passes whatever the numbers): on a CPU cheaper than every start at once (a
        pass costs a T-th of it), but each pass asks the host whether an edge still runs."""
        b, e, t, _ = feats.shape
        start = torch.zeros(b, e, dtype=torch.long, device=feats.device)
        exists = torch.ones(b, e, device=feats.device)  # segment k's straight-through existence
        # the drawn ends, summed over segments
        ends = feats.new_zeros(b, e, t + 1, dtype=torch.float32)
        kl = feats.new_zeros(b, e, dtype=torch.float32)
        running = torch.ones(b, e, dtype=torch.bool, device=feats.device)
        at = self.candidates(feats)
        for _ in range(t):
            if not bool(running.any()):
                break
            logits = self.posterior_logits(feats, at, start)
            log_q = end_log_probs(logits, start, fixed, value)
            # the segment's first step (a finished edge's start is t)
            first = start.clamp(max=t - 1)
            held = types.gather(2, first[..., None, None].expand(-1, -1, 1, types.shape[-1]))
            seg_kl = self._kl(log_q, self.prior.of_start(steps, start), held.squeeze(2), start,
                              fixed, value)
            kl = kl + seg_kl * exists * running
            holds = (None if interaction is None
                     else interaction.gather(2, first.unsqueeze(-1)).squeeze(2))
            end, drawn = self._draw(log_q, logits, start, fixed, value, holds)
            ends = ends + drawn * running.unsqueeze(-1)
            # the next segment's existence: forced where the end is a fixed boundary, else the drawn
            # end's
            opens = drawn.gather(-1, end.unsqueeze(-1)).squeeze(-1)
            at_fixed = F.pad(fixed, (0, 1), value=True).gather(-1, end.unsqueeze(-1)).squeeze(-1)
            exists = torch.where(running, torch.where(at_fixed, 1.0, opens), exists)
            start = torch.where(running, end, start)
            running = start < t
        return ends, kl

    # --------------------------------------------------- the prior hazard, at every step and online
    def boundary(self, h_t: torch.Tensor, t: int, end: int, held: torch.Tensor | None = None,
                 age: torch.Tensor | None = None, draw: bool = False) -> torch.Tensor:
        """Online: [B, E] bool, where a new segment starts at step t: after the burn-in, where the
        prior hazard of the held type ``held`` at the segment's ``age`` ([B, E] long) passes
        ``online_threshold`` (``draw``: with the hazard's probability, a sampled future)."""
        if t <= self.observed:
            return torch.zeros(h_t.shape[:2], dtype=torch.bool, device=h_t.device)
        return fires(torch.sigmoid(self.prior.at(h_t, held, age)), self.online_threshold, draw)

    def boundary_fit(self, h_fwd: torch.Tensor, held: torch.Tensor,
                     present: torch.Tensor) -> torch.Tensor:
        """The prior hazard fitted at every free step to where the posterior's held type changes (a
        binary cross entropy, the posterior's types stopped): h_fwd [B, E, T, R], held [B, E, T]
        long, present [B, E, T] bool -> [B], per present edge-step. It trains the online boundary
        model where it is used: at every step, with the held type and the age of the run it is
        in."""
        t = held.shape[-1]
        # a new run of one type starts
        change = F.pad(held[..., 1:] != held[..., :-1], (1, 0), value=True)
        logits = self.prior.along(h_fwd, held, change)
        fixed, _ = self.forced(t, h_fwd.device, present)
        free = present & ~fixed
        # log-sigmoids, not BCE-with-logits: its gradient's sigmoid rounds by vector width
        y = change.float()
        nll = -(y * F.logsigmoid(logits) + (1 - y) * F.logsigmoid(-logits))
        return (nll * free).flatten(1).sum(1) / present.flatten(1).sum(1).clamp_min(1)

    def cut_kl(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, gate: torch.Tensor,
               free: torch.Tensor,
               steps: torch.Tensor, held: torch.Tensor | None = None) -> torch.Tensor:
        """The duration KL of a posterior certain of a given cut: -log p(cut) under the prior, mixed
        as the duration KL is (:class:`~dider.models.hazard.HazardPrior`), the held type's hazard
        read with ``held`` [B, E, T] long (each step's type; None: the mean over types)."""
        b = gate.float()
        typed = held is not None and self.prior.held
        logits = self.prior.along(h_fwd, held, gate) if typed else self.prior_logits(h_fwd)

        def nll(x: torch.Tensor) -> torch.Tensor:
            return -(b * F.logsigmoid(x) + (1 - b) * F.logsigmoid(-x))

        per_step = ((1 - self.rate_mix) * nll(logits)
                    + self.rate_mix * nll(torch.full_like(logits, self.rate_logit)))
        return (per_step * free).flatten(1).sum(1) / steps
