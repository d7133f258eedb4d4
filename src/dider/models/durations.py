"""Duration plugins: how each edge's time axis is cut into segments of one interaction type.

Every plugin offers
- ``segment(h_fwd, h_rev, x, progress, present) -> Segmentation`` for training and posterior
  inference over a whole clip (``progress``: where training stands, for annealed schedules;
  ``present``: [B, E, T] bool, the edges present at each step, None when all are: a slot that an
  edge enters part-way is split there, so the type held after an entry is read where the edge is
  present and its edge KL counts; the durations stand),
- ``next_duration(h_t, t, end) -> [B, E] long`` for online inference and roll-outs: when an edge's
  segment ends at step t, how many steps its next segment lasts (read from the past only).

Shapes: h_fwd, h_rev [B, E, T, R]; x [B, T+1, N, D]; h_t [B, E, R].
"""

from __future__ import annotations

import math
from typing import ClassVar

import torch
from torch import nn

from dider.models.losses import gaussian_kl
from dider.models.plugins import Progress
from dider.models.segments import Segmentation, entries
from dider.validation import (
    FRACTION_OF_TRAINING,
    Rule,
    above,
    at_least,
    check_settings,
    integer,
    one_of,
    optional,
    within,
    within_open,
)


class PerStepDuration(nn.Module):
    """DNRI: every step is its own segment (K = T slots of length 1)."""

    def segment(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, x: torch.Tensor,
                progress: Progress = Progress(),
                present: torch.Tensor | None = None) -> Segmentation:
        b, e, t, _ = h_fwd.shape
        start = torch.arange(t, device=h_fwd.device).expand(b, e, t)
        valid = torch.ones(b, e, t, dtype=torch.bool, device=h_fwd.device)
        return Segmentation(start, valid, None, h_fwd.new_zeros(b, dtype=torch.float32))

    def next_duration(self, h_t: torch.Tensor, t: int, end: int) -> torch.Tensor:
        return torch.ones(h_t.shape[:2], dtype=torch.long, device=h_t.device)


class StaticDuration(nn.Module):
    """NRI-style static graph: one segment per edge covering the whole clip (where agents come and
    go, one per stretch of the edge's presence: a segment starts where the edge enters)."""

    def segment(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, x: torch.Tensor,
                progress: Progress = Progress(),
                present: torch.Tensor | None = None) -> Segmentation:
        b, e, t, _ = h_fwd.shape
        start = torch.zeros(b, e, 1, dtype=torch.long, device=h_fwd.device)
        valid = torch.ones(b, e, 1, dtype=torch.bool, device=h_fwd.device)
        assign = h_fwd.new_ones(b, e, t, 1, dtype=torch.float32)
        fixed = torch.ones(b, e, t, dtype=torch.bool, device=h_fwd.device)  # no boundary is chosen
        seg = Segmentation(start, valid, assign, h_fwd.new_zeros(b, dtype=torch.float32),
                           fixed=fixed)
        if present is None:
            return seg
        static = h_fwd.is_cuda if self.sync_free is None else self.sync_free
        return seg.split_at(entries(present), static)  # one type per stretch of presence

    def next_duration(self, h_t: torch.Tensor, t: int, end: int) -> torch.Tensor:
        return torch.full(h_t.shape[:2], max(end - t, 1), dtype=torch.long, device=h_t.device)

    # Where agents come and go, the slots split at entries in a shape fixed in advance (True: no
    # host synchronisation) or as many as needed (False, the CPU's choice); None picks by device.
    # The same cut.
    sync_free: bool | None = None


class LearnedDuration(nn.Module):
    """DIDER's duration module: a Gaussian latent per segment sets the fraction of the remaining
    steps that the segment lasts.

    For each edge and slot k (a Python loop over the slots, vectorised over B x E, that ends once
    every edge's slots cover the clip): features at the slot's first step give mu = tanh(f_mu(h)),
    sigma = sigma_min + (1 - sigma_min) * sigmoid(f_sigma(h)); z = mu + sigma * eps (z = mu in
    eval); rho = clamp((z + 1) / 2, rho_min, 1); d = max(rho * T_remaining, min_duration); the last
    slot runs to the end. The duration KL is against the fixed prior N(prior_mu, prior_sigma^2)
    (prior_mu -0.6: rho = 0.2 at the prior's mean). An edge has at most one slot per step.

    How this implementation settles what the paper leaves open:
    - tanh lets z and d go negative: rho maps z to a fraction in [rho_min, 1];
    - sigma could collapse to 0: it is a std with a floor ``sigma_min``;
    - continuous d against discrete steps: step j belongs to slot k when s_k <= j < s_{k+1} (hard,
      exact one-hot in the forward pass); the gradient reaches the boundaries through a soft step
      sigmoid((j + 0.5 - s) / tau_s), straight-through; tau_s anneals from ``tau_start`` to
      ``tau_end`` over the first ``tau_anneal`` of training;
    - the boundary step starts the new segment and its latents are read there;
    - where agents come and go (``present``), a slot that its edge enters part-way is split at the
      entry: the type held from there on is read at the entry (an absent edge's features say
      nothing), the drawn durations stand. Online, :meth:`RelationalVAE.advance_edges` re-reads the
      type at an entry likewise.

    ``source`` picks what the duration is read from: ``past`` (DIDER: the forward LSTM state,
    online, usable when forecasting) or ``future`` (DIDER with SKID: the reverse LSTM state, i.e.
    the whole remaining trajectory). When forecasting there is no future (the paper evaluates every
    model online), so SKID's durations then come from the same head fed the past-only (forward LSTM)
    state. ``fixed_duration`` replaces the latent by a constant number of steps (1 reproduces DNRI
    exactly).
    """

    SETTINGS: ClassVar[dict[str, Rule]] = {
        "rnn_hidden": integer(1), "hidden": integer(1), "source": one_of("past", "future"),
        "min_duration": at_least(1, " step"), "rho_min": within(0.0, 1.0),
        "sigma_min": within_open(0.0, 1.0), "prior_sigma": above(0), "tau_start": above(0),
        "tau_end": above(0), "tau_anneal": FRACTION_OF_TRAINING,
        "fixed_duration": optional(at_least(1)), "burn_in": optional(at_least(1)),
    }

    def __init__(
        self,
        rnn_hidden: int = 64,
        hidden: int = 64,
        source: str = "past",
        min_duration: float = 1.0,
        rho_min: float = 0.0,
        sigma_min: float = 1e-2,
        prior_mu: float = -0.6,
        prior_sigma: float = 1.0,
        tau_start: float = 1.5,
        tau_end: float = 0.5,
        tau_anneal: float = 1.0,
        fixed_duration: int | None = None,
        sigma_init: float = 0.5,
        burn_in: int | None = None,
    ) -> None:
        super().__init__()
        check_settings(self, locals(), {"sigma_init": (sigma_init, within_open(sigma_min, 1.0))})
        self.source, self.fixed_duration = source, fixed_duration
        self.min_duration, self.rho_min, self.sigma_min = float(min_duration), rho_min, sigma_min
        self.prior_mu, self.prior_sigma = prior_mu, prior_sigma
        self.tau_start, self.tau_end = tau_start, tau_end
        self.tau_anneal = tau_anneal
        # Transitions 0..burn_in-2 only lead up to the last observed frame: one segment of their
        # own, and the first learned segment starts at transition burn_in-1, read from
        # x_0..x_{burn_in-1}.
        self.observed = 0 if burn_in is None or fixed_duration is not None else burn_in - 1
        self.head = nn.Sequential(nn.Linear(rnn_hidden, hidden), nn.ELU(), nn.Linear(hidden, 2))
        # Every slot's pass, also once the slots cover the clip (True: no host synchronisation, the
        # form a CUDA graph captures; the slots past the end hold no step), or stop there (False:
        # the CPU's choice); None picks by device. Both give the same cut.
        self.sync_free: bool | None = None
        # start at the prior's mean fraction, with a small spread, not at rho = 0.5 +- 0.25
        with torch.no_grad():
            self.head[-1].bias[0] = math.atanh(max(min(prior_mu, 0.99), -0.99))
            self.head[-1].bias[1] = math.log((sigma_init - sigma_min) / (1 - sigma_init))

    def tau(self, progress: Progress) -> float | torch.Tensor:
        """The soft-step temperature: annealed linearly over the first ``tau_anneal`` of training (a
        tensor where ``progress.values`` gives it)."""
        frac = min(1.0, progress.fraction / self.tau_anneal) if self.tau_anneal > 0 else 1.0
        return progress.value("tau", self.tau_start + (self.tau_end - self.tau_start) * frac)

    def gaussian(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """h [..., R] -> mu, sigma [...] of the duration latent."""
        # fp32 under autocast: in bf16 a boundary near step 49 would move in quarter steps
        raw_mu, raw_sigma = self.head(h).float().unbind(-1)
        return torch.tanh(raw_mu), self.sigma_min + (1 - self.sigma_min) * torch.sigmoid(raw_sigma)

    def features(self, h_fwd: torch.Tensor, h_rev: torch.Tensor) -> torch.Tensor:
        """What the head reads, [B, E, T, R]: the past (forward LSTM) or, for SKID, the remaining
        trajectory (reverse LSTM)."""
        return h_fwd if self.source == "past" else h_rev

    def cut_kl(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, gate: torch.Tensor,
               free: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
        """The duration KL of a posterior certain of a given cut: -log of the prior's probability of
        the latents that give exactly its slot lengths, summed over the learned slots. A slot of L
        steps at s (T - s remaining) needs d = max(rho (T - s), min_duration) in (L - 1, L] (the
        last slot: d > L - 1), i.e. z in an interval; the prior N(prior_mu, prior_sigma^2) gives its
        probability. gate [B, E, T] bool (slot starts), free [B, E, T] bool (unused: the learned
        slots are those from the burn-in's end on), steps [B] -> [B]. Slot starts are integers here,
        where the model's are continuous: the durations are rounded up."""
        if self.fixed_duration is not None:
            return h_fwd.new_zeros(h_fwd.shape[0], dtype=torch.float32)
        t = gate.shape[-1]
        step = torch.arange(t, device=gate.device)
        # the first start at or after each step
        nxt = torch.where(gate, step, t).flip(-1).cummin(-1).values.flip(-1)
        nxt = torch.nn.functional.pad(nxt[..., 1:], (0, 1), value=t)  # ... strictly after it
        length, remaining = (nxt - step).float(), (t - step).float()
        prior = torch.distributions.Normal(self.prior_mu, self.prior_sigma)

        # the latent whose fraction of the remaining steps is d
        def z_of(d: torch.Tensor) -> torch.Tensor:
            return 2 * d / remaining - 1

        lo = torch.where(length - 1 >= self.min_duration, z_of(length - 1),
                         torch.full_like(length, -torch.inf))
        hi = torch.where(nxt >= t, torch.full_like(length, torch.inf), z_of(length))
        mass = (prior.cdf(hi) - prior.cdf(lo)).clamp_min(1e-12)
        learned = gate & (step >= self.observed)
        return (-mass.log() * learned).flatten(1).sum(1) / steps

    def fraction(self, z: torch.Tensor) -> torch.Tensor:
        return ((z + 1) / 2).clamp(self.rho_min, 1.0)

    def segment(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, x: torch.Tensor,
                progress: Progress = Progress(),
                present: torch.Tensor | None = None) -> Segmentation:
        b, e, t, _ = h_fwd.shape
        feats = self.features(h_fwd, h_rev)
        fixed = self.fixed_duration
        span = min(self.observed, t)  # the observed burn-in span: slot 0, no duration latent
        learned = t - span
        slots = (learned if fixed is None else -(-t // fixed)) if learned > 0 else 0
        s = h_fwd.new_zeros(b, e, dtype=torch.float32)  # continuous start of the current slot
        bounds, starts, mus, sigmas = [s], [], [], []
        if span > 0:
            starts.append(s.long())
            s = s + span
            bounds.append(s)
        # the head at every step in one call; each slot reads its first step's
        if fixed is None and slots > 0:
            mu_all, sigma_all = self.gaussian(feats)  # [B, E, T]
        every_slot = h_fwd.is_cuda if self.sync_free is None else self.sync_free
        for k in range(slots):
            # every edge's slots already cover the clip
            if k > 0 and not every_slot and not bool((s < t).any()):
                break
            start = s.detach().ceil().long().clamp(max=t - 1)  # first integer step of the slot
            starts.append(start)
            remaining = t - s
            if fixed is not None:
                d = torch.full_like(s, float(fixed))
            else:
                at = start.unsqueeze(-1)
                mu, sigma = mu_all.gather(2, at).squeeze(2), sigma_all.gather(2, at).squeeze(2)
                z = mu + sigma * torch.randn_like(mu) if self.training else mu
                d = torch.maximum(self.fraction(z) * remaining,
                                  torch.full_like(s, self.min_duration))
                mus.append(mu)
                sigmas.append(sigma)
            d = remaining if k == slots - 1 else torch.minimum(d, remaining)
            s = s + d
            bounds.append(s)
        assign, hard = self._assignment(torch.stack(bounds, dim=-1), t, self.tau(progress))
        valid = hard.sum(2) > 0  # slots holding at least one step (a slot past the end holds none)
        kl, sigma = h_fwd.new_zeros(b, dtype=torch.float32), None
        if mus:  # summed over an edge's segments, divided by its steps: the edge KL's convention
            learned_valid = valid[..., len(starts) - len(mus):]
            mu, sd = torch.stack(mus, -1), torch.stack(sigmas, -1)
            kl = ((gaussian_kl(mu, sd, self.prior_mu, self.prior_sigma) * learned_valid).flatten(1)
                  .sum(1) / (e * t))
            sigma = (sd.detach() * learned_valid).sum() / learned_valid.sum().clamp_min(1)
        step = torch.arange(t, device=h_fwd.device)
        fixed_steps = step <= self.observed  # the first step, and the burn-in span's end
        if present is not None:  # a slot starts where an edge enters; no choice where it is absent
            fixed_steps = fixed_steps | entries(present) | ~present
        seg = Segmentation(torch.stack(starts, dim=-1), valid, assign, kl, sigma, fixed=fixed_steps)
        return seg if present is None else seg.split_at(entries(present), every_slot)

    def _assignment(self, bounds: torch.Tensor, t: int,
                    tau: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Continuous boundaries [B, E, S+1] -> step-to-slot assignment [B, E, T, S]: exactly
        one-hot in the forward pass, with the gradient of a soft step to every boundary
        (straight-through). Returns (assignment, its hard part)."""
        j = torch.arange(t, device=bounds.device, dtype=bounds.dtype)[:, None]  # [T, 1]
        lo, hi = bounds[..., None, :-1], bounds[..., None, 1:]  # [B, E, 1, S]
        hard = ((j >= lo.detach()) & (j < hi.detach())).to(bounds.dtype)
        if not torch.is_grad_enabled() or not bounds.requires_grad:
            return hard, hard
        above = torch.sigmoid((j + 0.5 - bounds[..., None, :]) / tau)  # [B, E, T, S+1]
        soft = above[..., :-1] - above[..., 1:]
        return hard + (soft - soft.detach()), hard  # soft - soft.detach() is exactly 0 forward

    def next_duration(self, h_t: torch.Tensor, t: int, end: int) -> torch.Tensor:
        remaining = float(end - t)
        if self.fixed_duration is not None:
            return torch.full(h_t.shape[:2], self.fixed_duration, dtype=torch.long,
                              device=h_t.device)
        if t < self.observed:  # inside the burn-in: its span ends where the forecast starts
            return torch.full(h_t.shape[:2], self.observed - t, dtype=torch.long, device=h_t.device)
        # SKID: the head trained on the remaining trajectory, fed the past
        rho = self.fraction(self.gaussian(h_t)[0])
        return (rho * remaining).round().clamp_min(self.min_duration).long()
