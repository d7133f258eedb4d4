"""The relational VAE's objective, built from term objects chosen in the ``model/net/objective``
config group.

Each term reads a teacher-forced pass (:class:`~dider.models.inference.Inference`) and its batch and
returns one value per clip; the objective weighs them:

    loss = NLL + sum_i weight_i * w_i * |term_i - C_i|

where w_i is the KL warm-up's weight (ramped 0 -> 1 over ``kl_warmup`` of training, Bowman et al.)
for the terms that warm up, 1 for the NLL, and C_i a capacity ramped 0 -> ``capacity`` over
``capacity_ramp`` of training (beta-VAE, Burgess et al.; 0 by default). A new term is one class here
(or anywhere importable) and one entry in a ``conf/model/net/objective`` file. Each term declares
its settings' checks once (``SETTINGS``): the constructor applies them, and the preflight applies
them to the config before any work starts.

Shapes: B batch, E edges, T-1 transitions, K edge types, S segment slots.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import nn

from dider.models.inference import Inference
from dider.models.losses import capacity, categorical_kl, categorical_kl_probs
from dider.models.plugins import Progress
from dider.models.prior import fixed_log_probs
from dider.validation import (
    FRACTION_OF_TRAINING,
    NUM_TYPES,
    Rule,
    above,
    at_least,
    check_settings,
    integer,
    node_or_null,
    one_of,
    within_open,
)

Batch = Mapping[str, torch.Tensor]


class Term(nn.Module):
    """One term of the objective: ``forward(out, batch) -> [B]``, counted with ``weight`` (and
    ``capacity``).

    ``warms_up``: weighted by the KL warm-up (the KL terms and what is fitted to the posterior).
    ``in_nelbo``: counted, at its weight and without schedules, in ``nelbo``, the objective that
    selects checkpoints. ``STATS``: the figures ``stats`` gives beside the value, logged as
    ``<term>/<stat>``, outside the loss."""

    warms_up: ClassVar[bool] = True
    in_nelbo: ClassVar[bool] = True
    STATS: ClassVar[tuple[str, ...]] = ()
    SETTINGS: ClassVar[dict[str, Rule]] = {"weight": at_least(0), "capacity": at_least(0)}

    def __init__(self, weight: float = 1.0, capacity: float = 0.0) -> None:
        super().__init__()
        check_settings(self, locals())  # those its class declares: the NLL has neither
        self.weight, self.capacity = float(weight), float(capacity)

    def forward(self, out: Inference, batch: Batch) -> torch.Tensor:
        raise NotImplementedError

    def stats(self, out: Inference) -> dict[str, torch.Tensor]:
        """The figures named in ``STATS``, each [B] (a batch figure repeated per clip)."""
        return {}


def per_edge_step(values: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
    """values [B, E, ...] (0 where the edge is absent) -> their sum over a clip divided by its
    present edge-steps (present [B, E, T-1] bool) [B]: with one-step segments, DNRI's mean over
    (step, edge)."""
    return values.flatten(1).sum(1) / present.flatten(1).sum(1).clamp_min(1)


class EdgeKL(Term):
    """KL(q || p) of the edge types against the learned (or fixed) prior, per segment, summed over
    an edge's segments and divided by its present steps. ``count``: a segment's KL once
    (``per_segment``, the paper's sum over segments) or once per step it holds (``per_step``, the
    weight DNRI's per-step KL gives a type held that long)."""

    SETTINGS = Term.SETTINGS | {"count": one_of("per_segment", "per_step")}

    def __init__(self, weight: float = 1.0, capacity: float = 0.0,
                 count: str = "per_segment") -> None:
        super().__init__(weight, capacity)
        check_settings(self, locals())
        self.count = count

    def forward(self, out: Inference, batch: Batch) -> torch.Tensor:
        seg = out.seg
        at_start = out.present.gather(2, seg.start)
        # [B, E, S]
        kl = categorical_kl(out.posterior_logits, out.prior_logits) * at_start * seg.slot_weight
        if self.count == "per_step":
            kl = kl * seg.num_steps_per_slot
        return per_edge_step(kl, out.present)


class DurationKL(Term):
    """The duration plugin's KL (its posterior against its prior, per edge-step; 0 without a
    duration latent)."""

    def forward(self, out: Inference, batch: Batch) -> torch.Tensor:
        return out.seg.kl


class Sparsity(Term):
    """A KL against a fixed prior [no_edge_prob, (1 - no_edge_prob) / (K - 1), ...] that makes
    marking an edge cost. ``form``: ``mean_edges`` (DNRI's: the KL of the edges' mean type
    distribution at each step, which a step with fewer interacting edges than the budget pays for
    marking one more) or ``per_edge`` (NRI's: the mean over edge-steps of each one's KL, so every
    marked edge-step costs log(no_edge_prob / rest) more than an unmarked one, none is paid for)."""

    SETTINGS = {"weight": at_least(0), "no_edge_prob": within_open(0.0, 1.0),
                "form": one_of("mean_edges", "per_edge"), "num_types": NUM_TYPES}

    def __init__(self, weight: float = 1.0, no_edge_prob: float = 0.9, form: str = "mean_edges",
                 num_types: int = 2) -> None:
        super().__init__(weight)
        check_settings(self, locals())
        self.form = form
        self.register_buffer("log_probs", fixed_log_probs(num_types, no_edge_prob),
                             persistent=False)

    def forward(self, out: Inference, batch: Batch) -> torch.Tensor:
        return self.of(out.probs, out.present)

    def of(self, probs: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """probs [B, E, T-1, K] (each step's posterior), present [B, E, T-1] bool -> [B]."""
        if self.form == "per_edge":
            return per_edge_step(categorical_kl_probs(probs, self.log_probs) * present, present)
        w = present.unsqueeze(-1).to(probs.dtype)
        mean_q = (probs * w).sum(1) / w.sum(1).clamp_min(1)  # [B, T-1, K]
        return categorical_kl_probs(mean_q, self.log_probs).mean(-1)


class Indifference(Term):
    """A prior that prefers "none" where the likelihood cannot tell the types apart: every edge-step
    the posterior holds an interaction at costs ``weight`` (times its probability) where the
    decoder's evidence for it is below ``threshold`` nats (the receiver's one-step NLL with the edge
    at "none" minus at its best interaction type, every other edge as drawn, the gradient stopped:
    the decoder's ``edge_evidence``). Where the evidence is there the term costs nothing, so it
    trims what the likelihood leaves to the KL terms (a run held on before an interaction starts or
    after it ends) without taxing the interactions themselves, as a heavier sparsity term would.

    ``weighting: backed_share`` scales the term by the batch's backed share (:meth:`stats`;
    detached): the part of the held interaction mass whose evidence passes the threshold. Until the
    decoder has learned what an interaction does, nothing held has evidence and the term is off by
    itself, at any budget; charged at full weight from the first step it would hold every edge at
    "none", where the message network gets no gradient and never learns the interaction. As the term
    trims what has no evidence the share grows, and the term with it. ``fixed`` weighs it fully once
    both ``after`` (a share of training) and ``from_step`` (optimiser steps) have passed. The
    decoder learns an interaction after a number of optimiser steps set by the learning rate, not by
    the run's length, so a start in steps serves short and long runs alike where one share of
    training does not (too early in a short run, too late in a long one to recover the weak first
    and last steps of an interaction)."""

    needs_evidence: ClassVar[bool] = True
    STATS: ClassVar[tuple[str, ...]] = ("backed",)
    SETTINGS = {"weight": at_least(0), "threshold": above(0), "after": FRACTION_OF_TRAINING,
                "weighting": one_of("backed_share", "fixed"),
                "from_step": integer(0, " (optimiser steps)")}

    def __init__(self, weight: float = 1.0, threshold: float = 1.0, after: float = 0.0,
                 weighting: str = "backed_share", from_step: int = 0) -> None:
        super().__init__(weight)
        check_settings(self, locals())
        self.threshold, self.after, self.weighting = float(threshold), float(after), weighting
        self.from_step = int(from_step)

    def start(self, progress: Progress) -> int:
        """The optimiser step from which the term is charged: the later of ``after`` and
        ``from_step``; 0 where the run's length is unknown (a trained model, a pass outside a
        Trainer: every schedule at its end value)."""
        return max(progress.ramp_steps(self.after), self.from_step) if progress.total else 0

    def forward(self, out: Inference, batch: Batch) -> torch.Tensor:
        # a training pass before the start computes no evidence (Objective.reads_evidence)
        if out.evidence is None:
            return out.pred.new_zeros(out.pred.shape[0], dtype=torch.float32)
        marked, indifferent = self._held(out)
        cost = per_edge_step(marked * indifferent, out.present)
        return (cost * self._backed(marked, indifferent, out) if self.weighting == "backed_share"
                else cost)

    def stats(self, out: Inference) -> dict[str, torch.Tensor]:
        """``backed``: the share of the batch's held interaction mass whose evidence passes the
        threshold, over the edge-steps whose receiver is present at the next step (0 where nothing
        is held, or no evidence was computed), repeated per clip [B]."""
        if out.evidence is None:
            return {"backed": out.pred.new_zeros(out.pred.shape[0], dtype=torch.float32)}
        return {"backed": self._backed(*self._held(out), out).expand(out.pred.shape[0])}

    def _held(self, out: Inference) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (the held interaction probability on present edge-steps, the steps below the
        threshold), [B, E, T-1]."""
        if out.evidence is None:
            raise RuntimeError("the indifference term needs the pass's edge evidence "
                               "(Inference.evidence)")
        marked = (1.0 - out.probs[..., 0]) * out.present
        return marked, (out.evidence < self.threshold) & out.present

    @staticmethod
    def _backed(marked: torch.Tensor, indifferent: torch.Tensor, out: Inference) -> torch.Tensor:
        """The backed share, a detached device scalar (no host sync)."""
        scored = marked.detach() * torch.isfinite(out.evidence)
        return (scored * ~indifferent).sum() / scored.sum().clamp_min(1e-6)


class PriorFit(Term):
    """Outside the ELBO: fits the learned prior at every step to the posterior type held there, the
    posterior's gradient stopped. With segments the ELBO's KL trains the prior at segment starts
    only; forecasting reads it at every step. Warms up with the KL terms (at full weight from the
    first step the fit, through the encoder the prior and posterior share, would settle the
    posterior on a type that does no harm)."""

    in_nelbo = False

    def forward(self, out: Inference, batch: Batch) -> torch.Tensor:
        fit = categorical_kl_probs(out.probs.detach(), F.log_softmax(out.prior_step_logits, dim=-1))
        return per_edge_step(fit * out.present, out.present)


class BoundaryFit(Term):
    """Outside the ELBO: the duration plugin's online boundary model (the prior hazard, given the
    held type and the segment's age) fitted at every step to where the posterior's held type changes
    (its ``boundary_fit``; 0 for a plugin without one). The end KL trains it at segment starts only,
    against the posterior's end; forecasting reads it at every step. Warms up with the KL terms, as
    ``prior_fit`` does."""

    in_nelbo = False

    def forward(self, out: Inference, batch: Batch) -> torch.Tensor:
        if out.boundary_fit is None:
            return out.pred.new_zeros(out.pred.shape[0], dtype=torch.float32)
        return out.boundary_fit


class Objective(nn.Module):
    """The terms by name (``nll`` required; a term set to None is left out) and the schedules of
    their weights: ``kl_warmup`` and ``capacity_ramp``, fractions of training."""

    SETTINGS: ClassVar[dict[str, Rule]] = {"kl_warmup": FRACTION_OF_TRAINING,
                                           "capacity_ramp": FRACTION_OF_TRAINING}
    # the terms (the preflight's rule of the keys besides the settings)
    KEYWORDS: ClassVar[Rule] = node_or_null

    def __init__(self, kl_warmup: float = 0.0, capacity_ramp: float = 0.5,
                 **terms: Term | None) -> None:
        super().__init__()
        check_settings(self, locals())
        if "nll" not in terms or terms["nll"] is None:
            raise ValueError("model.net.objective: needs an `nll` term (the decoder's likelihood)")
        if wrong := [k for k, v in terms.items() if v is not None and not isinstance(v, Term)]:
            raise TypeError(f"model.net.objective: {wrong} are not dider.models.objective.Term "
                            "objects")
        self.kl_warmup, self.capacity_ramp = kl_warmup, capacity_ramp
        self.terms = nn.ModuleDict({k: v for k, v in terms.items() if v is not None})
        # a term that reads the decoder's evidence for each edge (the pass computes it only then)
        self.needs_evidence = any(getattr(t, "needs_evidence", False) for t in self.terms.values())

    def reads_evidence(self, progress: Progress) -> bool:
        """Whether a pass at ``progress`` computes the decoder's edge evidence: from the ``start``
        of a term that reads it. So only a training pass before that start skips it; validation and
        a pass outside a Trainer (the run's length unknown: every start is 0, and ``nelbo`` counts
        every term) and a graphed step (one captured graph for the whole run) always compute it."""
        if progress.values is not None:
            return self.needs_evidence
        # each has a ``start``
        readers = [t for t in self.terms.values() if getattr(t, "needs_evidence", False)]
        return any(progress.step >= t.start(progress) for t in readers)

    def values(self, out: Inference, batch: Batch) -> dict[str, torch.Tensor]:
        """Every term's value per clip: name -> [B], and each term's logged figures
        (``<term>/<stat>``, its ``stats``; outside the loss)."""
        values = {name: term(out, batch) for name, term in self.terms.items()}
        return (values | {f"{name}/{k}": v for name, term in self.terms.items()
                          for k, v in term.stats(out).items()})

    def names(self) -> list[str]:
        """The names :meth:`values` gives: the terms, then their figures (``<term>/<stat>``)."""
        return [*self.terms,
                *(f"{name}/{k}" for name, term in self.terms.items() for k in term.STATS)]

    def schedule(self, progress: Progress = Progress()) -> dict[str, float | torch.Tensor]:
        """The annealed weights at ``progress``: the KL warm-up's ``kl_weight``, each
        ``capacity/<term>`` that has one and ``on/<term>`` (0 or 1) for a term off early in training
        (tensors where ``progress.values`` gives them)."""
        ramp = progress.ramp_steps(self.capacity_ramp)
        out = {"kl_weight": capacity(progress.step, 1.0, progress.ramp_steps(self.kl_warmup))}
        out |= {f"capacity/{k}": capacity(progress.step, t.capacity, ramp)
                for k, t in self.terms.items()
                if t.capacity > 0}
        out |= {f"on/{k}": float(progress.step >= t.start(progress)) for k, t in self.terms.items()
                if hasattr(t, "start")}  # a term off early in training (its ``start``)
        return {k: progress.value(k, v) for k, v in out.items()}

    def forward(self, values: Mapping[str, torch.Tensor],
                progress: Progress = Progress()) -> dict[str, torch.Tensor]:
        """values: :meth:`values` -> ``loss``, each term's (and figure's) batch mean and ``nelbo``:
        the objective free of schedules and capacities (the terms ``in_nelbo`` at their weights),
        what selects checkpoints."""
        sched = self.schedule(progress)
        means = {name: v.mean() for name, v in values.items()}
        loss = means["nll"]
        nelbo = means["nll"].detach()
        for name, term in self.terms.items():
            if name == "nll":
                continue
            c = sched.get(f"capacity/{name}", 0.0)
            # tensor first: a schedule given as a device scalar (a graphed step) then rounds as a
            # Python float does
            weight = term.weight * sched.get(f"on/{name}", 1.0)
            loss = (loss + (means[name] - c)
                    .abs() * (sched["kl_weight"] if term.warms_up else 1.0) * weight)
            if term.in_nelbo:
                nelbo = nelbo + term.weight * means[name].detach()
        return {"loss": loss, **means, "nelbo": nelbo}

