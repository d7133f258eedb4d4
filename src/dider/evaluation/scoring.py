"""What a test run scores: forecast MSE per horizon, edge accuracy, segment statistics, switch-time
F1 and the inD consistency check, as one collection of torchmetrics (reduced over ranks under DDP).

Shapes: B batch, P predicted steps, N agents, D features, E edges, T-1 transitions.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn
from torchmetrics import Metric

from dider.data.batch import Batch, Normalizer
from dider.data.pairs import KIND_NAMES
from dider.evaluation.metrics import (
    BoundaryF1,
    EdgeAccuracy,
    HorizonDisplacement,
    HorizonMSE,
    InteractionRunLength,
    OwnCut,
    PairConsistency,
    SegmentStats,
)
from dider.evaluation.sampled import MinDisplacement, sampled_values
from dider.evaluation.structure import StructureRecovery
from dider.evaluation.type_meaning import TypeProfile, pair_features, profile_values
from dider.graph import edge_mask
from dider.models.inference import Inference

log = logging.getLogger(__name__)


@dataclass
class Forecast:
    """A roll-out over a whole clip after its burn-in, with what it is scored against."""

    pred: torch.Tensor  # [B, P, N, D]
    target: torch.Tensor  # [B, P, N, D]
    mask: torch.Tensor  # [B, P, N] bool: targets that exist
    types: torch.Tensor  # [B, E, T-1] long: the edge types the roll-out used
    # [B, P, N] long: each target's own horizon (per-agent burn-in), else None
    horizon: torch.Tensor | None


# Forecasts with given edges beside the model's own, to separate the decoder's error from the edge
# forecast's: ``posterior`` (edges inferred from the whole clip), ``oracle`` (the ground truth,
# where known).
EDGE_SOURCES = ("posterior", "oracle")


class TestMetrics(nn.Module):
    """update() per test batch, compute() once at the end: ``test/...`` name -> value."""

    def __init__(self, horizons: Sequence[int], num_types: int, samples: int = 0,
                 miss_threshold: float | None = None) -> None:
        super().__init__()
        self.samples = samples  # the sampled futures' count, K (0: none scored)
        self.sampled = MinDisplacement(horizons, miss_threshold)
        self.mse, self.mse_raw = HorizonMSE(horizons), HorizonMSE(horizons)
        # ADE / FDE of positions in data units, the model's and constant velocity's on the same
        # clips and masks: the bar a forecaster has to clear, in the units its users read.
        self.displacement = nn.ModuleDict({k: HorizonDisplacement(horizons)
                                           for k in ("model", "cv", "no_edges")})
        self.mse_by_edges = nn.ModuleDict({k: HorizonMSE(horizons) for k in EDGE_SOURCES})
        self.acc_posterior, self.acc_prior = EdgeAccuracy(), EdgeAccuracy()
        # The prior read at every step, as if it could re-decide each step (for DNRI it is
        # ``prior``): beside ``prior`` it shows what the online segments' holding costs and what the
        # prior itself knows.
        self.acc_prior_per_step = EdgeAccuracy()
        # The field's scores on NRI's systems: types matched to the true labels, and the AUROC of
        # the edge probability.
        self.structure = nn.ModuleDict({k: StructureRecovery(num_types)
                                        for k in ("posterior", "prior")})
        self.segments = SegmentStats()
        # Mean interaction run length and rate of the segments, the online prior and the truth: runs
        # that go on past the truth's end show here while they barely move the recalls.
        self.run_length = nn.ModuleDict({k: InteractionRunLength()
                                         for k in ("posterior", "prior", "truth")})
        self.boundary = BoundaryF1(tolerance=2)
        self.own_cut = OwnCut(tolerance=2)  # the duration plugin's own boundaries
        self.pairs = PairConsistency(num_types, num_kinds=len(KIND_NAMES))
        self.types = TypeProfile(num_types)  # what each posterior type means, in data units

    def update(self, *, batch: Batch, forecast: Forecast, posterior: torch.Tensor,
               prior: torch.Tensor, units: Callable[[torch.Tensor], torch.Tensor] | None = None,
               by_edges: dict[str, Forecast] | None = None,
               prior_per_step: torch.Tensor | None = None,
               own_cut: dict[str, torch.Tensor] | None = None, cv: Forecast | None = None,
               futures: torch.Tensor | None = None, no_edges: Forecast | None = None,
               posterior_probs: torch.Tensor | None = None) -> None:
        """posterior, prior: [B, E, T-1] long edge types inferred from the whole clip / online from
        the past. units: model states to the data's units (:func:`data_units` of the data's
        normaliser; None: the model's normalised units, and no ``test/mse_raw``). by_edges:
        forecasts driven by given edges, by their source (:data:`EDGE_SOURCES`). prior_per_step: [B,
        E, T-1] long, the prior's type at every step (no segments held). own_cut: the arguments of
        :meth:`OwnCut.update` (None: the model has no cut of its own). cv: the constant-velocity
        forecast of the same clips under the same protocol. futures: [B, K, P, N, D] the sampled
        forecasts (:meth:`~dider.models.vae.RelationalVAE.sample_futures`), scored in data units.
        no_edges: the model's own roll-out with every edge off (its decoder's dynamics alone), on
        the same clips. posterior_probs: [B, E, T-1, K] the posterior's type probabilities (for the
        AUROC of the edges)."""
        self.mse.update(forecast.pred, forecast.target, forecast.mask, forecast.horizon)
        for source, f in (by_edges or {}).items():
            self.mse_by_edges[source].update(f.pred, f.target, f.mask, f.horizon)
        raw = units is not None
        units = units or data_units(None)
        for name, f in {"model": forecast, "cv": cv, "no_edges": no_edges}.items():
            if f is not None:
                self.displacement[name].update(units(f.pred), units(f.target), f.mask, f.horizon)
        if raw:
            self.mse_raw.update(units(forecast.pred), units(forecast.target), forecast.mask,
                                forecast.horizon)
        if futures is not None:
            self.sampled.update(units(futures), units(forecast.target), forecast.mask,
                                forecast.horizon)
        # One rule for the edge-steps the type table and the interaction rates count: both agents
        # present at t and the receiver at t+1 (where its acceleration is defined).
        # [B, E, T-1, F], [B, E, T-1]
        features, steps = pair_features(units(batch["states"]), batch["mask"])
        self.types.update(posterior, features, steps)
        present = edge_mask(batch["mask"][:, :-1])  # [B, T-1, E]
        self.segments.update(posterior, present.any(1))
        self.run_length["posterior"].update(posterior, steps)
        self.run_length["prior"].update(prior, steps)
        if "edges" in batch:
            self.acc_posterior.update(posterior.transpose(1, 2), batch["edges"], present)
            self.acc_prior.update(prior.transpose(1, 2), batch["edges"], present)
            if prior_per_step is not None:
                self.acc_prior_per_step.update(prior_per_step.transpose(1, 2), batch["edges"],
                                               present)
            self.boundary.update(posterior, batch["edges"].transpose(1, 2))
            truth, keep = batch["edges"].transpose(1, 2), present.transpose(1, 2)
            self.structure["posterior"].update(posterior, truth, keep, posterior_probs)
            self.structure["prior"].update(prior, truth, keep)
            self.run_length["truth"].update(batch["edges"].transpose(1, 2), steps)
        if own_cut is not None:
            self.own_cut.update(**own_cut)
        if "pair_kind" in batch:
            self.pairs.update(posterior, batch["pair_kind"], present.transpose(1, 2))

    def compute(self) -> dict[str, torch.Tensor]:
        """Every metric that saw data, then reset them all."""
        out = displacement_values("test", self.displacement["model"], self.displacement["cv"])
        # what the edges add to the decoder's dynamics
        if (off := self.displacement["no_edges"]).update_count:
            (ade, _), (ade_off, _) = self.displacement["model"].compute(), off.compute()
            out |= {f"test/ade_vs_no_edges/h{h:02d}": a / b
                    for h, a, b in zip(off.horizons, ade, ade_off, strict=True)}
        if self.sampled.update_count:
            out |= sampled_values("test", self.sampled, self.samples)
        out |= horizon_values("test/mse", self.mse)
        if self.mse_raw.update_count:
            out |= horizon_values("test/mse_raw", self.mse_raw)
        for source, metric in self.mse_by_edges.items():
            if metric.update_count:
                out |= horizon_values(f"test/mse_{source}", metric)
        out["test/segments_per_edge"], out["test/switches_per_100"] = self.segments.compute()
        if self.boundary.update_count:
            out["test/boundary_f1"] = self.boundary.compute()
        if self.own_cut.update_count:
            out |= own_cut_values("test/segments", self.own_cut)
        runs = {k: m.compute() for k, m in self.run_length.items() if m.update_count}
        lengths = {f"test/run_length/{k}": v[0] for k, v in runs.items()}
        _warn_empty(lengths, "no step of any interaction type")
        out |= lengths | {f"test/interaction_rate/{k}": v[1] for k, v in runs.items()}
        for name, metric in {"posterior": self.acc_posterior, "prior": self.acc_prior,
                             "prior_per_step": self.acc_prior_per_step}.items():
            if metric.update_count:
                out |= edge_acc_values(f"test/edge_acc/{name}", metric)
        for name, metric in self.structure.items():
            if metric.update_count:
                values = metric.compute()
                out |= {f"test/edge_acc/{name}/{k}": values[k] for k in ("matched", "as_labelled")}
                if "auroc" in values:
                    out[f"test/edge_auroc/{name}"] = values["auroc"]
        if self.pairs.update_count:
            out |= self._consistency()
        if self.types.update_count:
            out |= profile_values("test", self.types)
        for metric in self.modules():
            if isinstance(metric, Metric):
                metric.reset()
        return out

    def _consistency(self) -> dict[str, torch.Tensor]:
        """test/consistency/{parked,opposite}/{share,type,edge_steps}; a kind with no edge-steps in
        the test split gets only its (zero) count, with a warning, rather than a made-up share."""
        share, dominant, total = self.pairs.compute()
        out = {}
        for k, name in KIND_NAMES.items():
            out[f"test/consistency/{name}/edge_steps"] = total[k - 1].float()
            if total[k - 1] > 0:
                out[f"test/consistency/{name}/share"] = share[k - 1]
                out[f"test/consistency/{name}/type"] = dominant[k - 1].float()
            else:
                log.warning("consistency check: no %s pairs in the test split (data.pairs sets the "
                            "rules)", name)
        return out


@torch.no_grad()
def seeded_forecast(pl_module: Any, states: torch.Tensor, mask: torch.Tensor, burn_in: int,
                    steps: int, chunk: int = 16) -> torch.Tensor:
    """The model's forecast after the first ``burn_in`` frames (agents present at its last frame
    carry on) as evaluation draws it: in eval mode, from ``eval_seed``, leaving the global random
    state alone, ``chunk`` clips at a time. states [S, T, N, D], mask [S, T, N] (any device) -> [S,
    steps, N, D] on the CPU."""
    model = pl_module.model
    was_training = model.training
    model.eval()
    device = torch.device(pl_module.device)
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        torch.manual_seed(int(pl_module.eval_seed))
        parts = [model.forecast_after(x.to(pl_module.device), m.to(pl_module.device), burn_in,
                                      steps).float().cpu()
                 for x, m in zip(states.split(chunk), mask.split(chunk), strict=True)]
    model.train(was_training)
    return torch.cat(parts)


def data_units(normalizer: Normalizer | None) -> Callable[[torch.Tensor], torch.Tensor]:
    """Maps model states [..., D] to the data's units in float64, relative to the normaliser's
    origin (identity without a normaliser): errors and distances are the same relative to any
    origin, and float64 keeps the digits that bf16 would round and the squares that float32 would
    overflow."""
    return ((lambda states: normalizer.denormalize(states.double())) if normalizer is not None
            else (lambda s: s))


def horizon_values(prefix: str, metric: HorizonMSE) -> dict[str, torch.Tensor]:
    """``prefix/hXX`` -> the metric's value at each of its horizons; NaN, with a warning naming it,
    for a horizon that no present agent reached (e.g. tracks shorter than the burn-in plus the
    horizon)."""
    values = metric.compute().reshape(-1)  # 0-d for a single horizon: torchmetrics squeezes it
    out = {f"{prefix}/h{h:02d}": v for h, v in zip(metric.horizons, values, strict=True)}
    _warn_empty(out, "no present agent reached this horizon")
    return out


def displacement_values(prefix: str, model: HorizonDisplacement,
                        cv: HorizonDisplacement) -> dict[str, torch.Tensor]:
    """``prefix/ade/hXX``, ``prefix/fde/hXX`` of the model, ``prefix/cv/ade/hXX``,
    ``prefix/cv/fde/hXX`` of constant velocity, and ``prefix/ade_vs_cv/hXX`` (the model's ADE over
    constant velocity's: below 1 beats it), for the metrics that saw data."""
    out: dict[str, torch.Tensor] = {}
    for name, metric in {"": model, "cv/": cv}.items():
        if metric.update_count:
            ade, fde = metric.compute()
            for h, a, f in zip(metric.horizons, ade, fde, strict=True):
                out[f"{prefix}/{name}ade/h{h:02d}"], out[f"{prefix}/{name}fde/h{h:02d}"] = a, f
    if model.update_count and cv.update_count:
        for h in model.horizons:
            out[f"{prefix}/ade_vs_cv/h{h:02d}"] = (
                out[f"{prefix}/ade/h{h:02d}"] / out[f"{prefix}/cv/ade/h{h:02d}"])
    _warn_empty(out, "no present agent reached this horizon")
    return out


def own_cut_values(prefix: str, metric: OwnCut) -> dict[str, torch.Tensor]:
    """``prefix/on_switch`` (the share of own boundaries where the held type changes; left out
    without an own boundary) and, with ground truth, ``prefix/boundary_f1`` (own boundaries against
    the true switches, +-2 steps, unmerged) and ``prefix/per_constant_edge`` (own boundaries per
    edge whose true type never switches)."""
    values = dict(zip(("on_switch", "boundary_f1", "per_constant_edge"), metric.compute(),
                      strict=True))
    # NaN: no own boundary / truth
    return {f"{prefix}/{k}": v for k, v in values.items() if not bool(torch.isnan(v))}


def edge_acc_values(prefix: str, metric: EdgeAccuracy) -> dict[str, torch.Tensor]:
    """``prefix/none`` and ``prefix/interaction``: recall per ground-truth class, NaN (with a
    warning) for a class with no edge-step."""
    none, interaction = metric.compute()
    out = {f"{prefix}/none": none, f"{prefix}/interaction": interaction}
    _warn_empty(out, "no ground-truth edge-step of this class")
    return out


def _warn_empty(values: dict[str, torch.Tensor], why: str) -> None:
    if empty := [k for k, v in values.items() if bool(torch.isnan(v))]:
        log.warning("%s: reported as NaN (%s)", ", ".join(empty), why)


# What the end-of-run table, the report and TensorBoard's HParams tab lead with: the forecast
# against constant velocity in data units.
LEADING = ("test/ade_vs_cv/", "test/ade/", "test/cv/ade/", "test/fde/", "test/cv/fde/")


def leading_first(names: Sequence[str]) -> list[str]:
    """Metric names sorted with :data:`LEADING`'s groups first, in that order, then the rest
    alphabetically."""
    def rank(name: str) -> tuple[int, str]:
        return next((i for i, p in enumerate(LEADING) if name.startswith(p)), len(LEADING)), name
    return sorted(names, key=rank)


def edges_help(ratio: float) -> bool:
    """Whether the edges earn their keep at an ``ade_vs_no_edges`` ratio: better than the edge-free
    roll-out by enough to show in the two decimals the ratio is reported with (a model that holds no
    interaction at all scores 0.9997x-0.9999x: float rounding, not help)."""
    return round(ratio, 2) < 1.0


def edges_verdict(metrics: Mapping[str, float]) -> str | None:
    """A warning when the edges do not earn their keep: the forecast with the model's own edges is
    no better than the same roll-out with every edge off (``.../ade_vs_no_edges/hXX`` not below 1.00
    at the longest horizon: :func:`edges_help`); None otherwise, or without the ratio."""
    ratios = dict(sorted((k.rsplit("/", 1)[1], float(v)) for k, v in metrics.items()
                         if "/ade_vs_no_edges/" in k and math.isfinite(float(v))))
    if not ratios or edges_help(ratios[list(ratios)[-1]]):
        return None
    text = ", ".join(f"{h} {v:.2f}x" for h, v in ratios.items())
    return ("the edges do not earn their keep: the forecast is no better than the same model's "
            f"with every edge off (position ADE over the edge-free roll-out's: {text}); read its "
            "edge types with care")


def cv_verdict(metrics: Mapping[str, float]) -> tuple[str, bool] | None:
    """One line on whether the forecast beats constant velocity (position ADE in data units, on the
    same clips: the ``.../ade_vs_cv/hXX`` values of :func:`displacement_values`) with the ratio per
    horizon, and whether it beats it at the longest horizon (one step ahead constant velocity is
    often near exact: the forecast earns its keep further out); None when the run has no ratio."""
    ratios = dict(sorted((k.rsplit("/", 1)[1], float(v)) for k, v in metrics.items()
                         if "/ade_vs_cv/" in k and math.isfinite(float(v))))
    if not ratios:
        return None
    text = ", ".join(f"{h} {v:.2f}x" for h, v in ratios.items())
    longest = list(ratios)[-1]
    worse = [h for h, v in ratios.items() if v >= 1.0]
    if ratios[longest] >= 1.0:
        return (f"the forecast is NOT better than constant velocity at {', '.join(worse)} "
                f"(position ADE over constant velocity's on the same clips: {text}); its edges "
                "explain no motion that constant velocity misses there", False)
    where = "at every horizon" if not worse else f"at {longest} but not at {', '.join(worse)}"
    return (f"the forecast beats constant velocity {where} (position ADE over constant velocity's: "
            f"{text})"), True


def own_cut_inputs(out: Inference,
                   batch: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor | None] | None:
    """What :class:`~dider.evaluation.metrics.OwnCut` reads of a pass: each step's slot, the held
    types, the free steps and (where known) the true types, each [B, E, T-1]; None for a plugin
    without a cut of its own (a slot per step)."""
    if out.seg.assign is None:
        return None
    present = edge_mask(batch["mask"][:, :-1]).transpose(1, 2)
    truth = batch["edges"].transpose(1, 2) if "edges" in batch else None
    return {"slot": out.seg.step_slot(), "held": out.posterior_types(),
            "free": out.seg.free(present), "truth": truth}
