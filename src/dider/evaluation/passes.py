"""What validation, test and prediction score a batch with, beside the LightningModule that runs
them: the roll-outs under the forecast protocol (the model's own edges, given ones, none; its
decoder or constant velocity's) and the metrics they feed. Each pass is a module of metrics (moved
with the LightningModule, reduced over ranks) with an ``update`` taking exactly what it scores and a
``values`` (or ``compute``) read once at the epoch's end.

Shapes: B batch, T frames, N agents, D features, E edges, K edge types, P predicted steps.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import nn
from torchmetrics import Metric

from dider.data.batch import Batch
from dider.evaluation.metrics import EdgeAccuracy, HorizonDisplacement, HorizonMSE, OwnCut
from dider.evaluation.scoring import (
    Forecast,
    TestMetrics,
    data_units,
    displacement_values,
    edge_acc_values,
    horizon_values,
    own_cut_inputs,
    own_cut_values,
)
from dider.evaluation.type_meaning import TypeProfile, pair_features, profile_values
from dider.graph import edge_mask
from dider.models.baselines import ConstantVelocity
from dider.models.inference import Inference
from dider.models.vae import RelationalVAE
from dider.protocol import agent_horizons, scored_targets
from dider.settings import ForecastProtocol

# model states [..., D] -> the data's units in float64
# (:func:`~dider.evaluation.scoring.data_units`); None: a pass without the data's normaliser, scored
# in the model's normalised units
Units = Callable[[torch.Tensor], torch.Tensor] | None


def roll_out(model: RelationalVAE, batch: Batch, protocol: ForecastProtocol,
             edges: torch.Tensor | None = None,
             decoder: nn.Module | None = None, edges_off: bool = False) -> Forecast:
    """The roll-out over the whole clip after the burn-in (each agent's own burn-in in ``per_agent``
    mode, where each target carries its own horizon; frame p is horizon p + 1 in ``global`` mode),
    with the model's own edges, given ones (edges [B, E, T-1]) or none at all (``edges_off``), with
    the model's decoder or another one."""
    x, mask, b, mode = batch["states"], batch["mask"], protocol.burn_in, protocol.burn_in_mode
    pred, types = model.rollout(x, mask, b, x.shape[1] - b, mode, edges, decoder,
                                edges_off=edges_off)
    horizon = agent_horizons(mask, b)[:, b:] if mode == "per_agent" else None
    return Forecast(pred, x[:, b:], scored_targets(mask, b, mode), types, horizon)


class ValidationPass(nn.Module):
    """Validation's forecast and edges: the normalised MSE per horizon, the position ADE / FDE in
    data units beside constant velocity's (a recipe is chosen on validation), the own cut's
    boundaries and, with ground truth, the posterior's recalls."""

    def __init__(self, protocol: ForecastProtocol) -> None:
        super().__init__()
        self.protocol = protocol
        self.mse = HorizonMSE(protocol.horizons)
        self.ade = nn.ModuleDict({k: HorizonDisplacement(protocol.horizons)
                                  for k in ("model", "cv")})
        self.acc, self.cut = EdgeAccuracy(), OwnCut(tolerance=2)
        self.constant_velocity = ConstantVelocity()

    def update(self, model: RelationalVAE, batch: Batch, out: Inference, units: Units) -> None:
        """A hard :meth:`~dider.models.vae.RelationalVAE.infer` pass ``out`` of ``batch`` and its
        roll-outs."""
        units = units or data_units(None)
        f = roll_out(model, batch, self.protocol)
        self.mse.update(f.pred, f.target, f.mask, f.horizon)
        cv = roll_out(model, batch, self.protocol, torch.zeros_like(out.posterior_types()),
                      self.constant_velocity)
        for name, pred in {"model": f.pred, "cv": cv.pred}.items():
            self.ade[name].update(units(pred), units(f.target), f.mask, f.horizon)
        if (cut := own_cut_inputs(out, batch)) is not None:
            self.cut.update(**cut)
        if "edges" in batch:
            self.acc.update(out.posterior_types().transpose(1, 2), batch["edges"],
                            edge_mask(batch["mask"][:, :-1]))

    def names(self) -> set[str]:
        """Every name :meth:`values` can return (some only where the data allow: a horizon no agent
        reaches, an own cut without a boundary, data without ground truth)."""
        hs = [f"h{int(h):02d}" for h in self.protocol.horizons]
        return {f"val/{kind}/{h}" for kind in ("mse", "ade", "fde", "cv/ade", "cv/fde", "ade_vs_cv")
                for h in hs} | {
                    "val/segments/on_switch", "val/segments/boundary_f1",
                    "val/segments/per_constant_edge",
                    "val/edge_acc/posterior/none", "val/edge_acc/posterior/interaction"}

    def values(self) -> dict[str, torch.Tensor]:
        """``val/mse/hXX``, ``val/ade/hXX`` ..., and where the data allow the recalls and own-cut
        scores; resets."""
        out = (horizon_values("val/mse", self.mse) | displacement_values("val", self.ade["model"],
                                                                         self.ade["cv"]))
        if self.acc.update_count:
            out |= edge_acc_values("val/edge_acc/posterior", self.acc)
        if self.cut.update_count:
            out |= own_cut_values("val/segments", self.cut)
        _reset(self)
        return out


class TestPass(nn.Module):
    """Every roll-out a test batch is scored with (the model's own, with the posterior's and the
    true edges, constant velocity's, the edge-free one, the sampled futures) and
    :class:`~dider.evaluation.scoring.TestMetrics`."""

    __test__ = False  # not a pytest class

    def __init__(self, protocol: ForecastProtocol, num_types: int) -> None:
        super().__init__()
        self.protocol = protocol
        self.metrics = TestMetrics(protocol.horizons, num_types, protocol.samples,
                                   protocol.miss_threshold)
        self.constant_velocity = ConstantVelocity()

    def update(self, model: RelationalVAE, batch: Batch, out: Inference,
               units: Units) -> dict[str, torch.Tensor]:
        """Scores a hard pass ``out`` of ``batch`` -> its per-clip outputs for the export and figure
        callbacks: ``segments`` (posterior types, -1 where the edge is absent), ``probs`` (their
        probability), ``prior`` (online types) and ``per_step`` (per-step posterior types), each [B,
        E, T-1]."""
        p = self.protocol
        present = edge_mask(batch["mask"][:, :-1]).transpose(1, 2)  # [B, E, T-1]
        posterior, prior = out.posterior_types(), model.online_types(out.h_fwd, present)
        none = torch.zeros_like(posterior)
        # in this order: the model's own roll-out draws its edges first (the draws of eval_seed a
        # test pass reads)
        forecast = roll_out(model, batch, p)
        by_edges = {"posterior": roll_out(model, batch, p, posterior)}
        if "edges" in batch:
            by_edges["oracle"] = roll_out(model, batch, p, batch["edges"].transpose(1, 2))
        prior_per_step = model.prior(out.h_fwd).argmax(-1)
        cv = roll_out(model, batch, p, none, self.constant_velocity)
        futures = None
        if p.samples:  # drawn aside: the other metrics' draws are those of a test pass without them
            device = batch["states"].device
            with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
                futures = model.sample_futures(batch["states"], batch["mask"], p.burn_in,
                                               batch["states"].shape[1] - p.burn_in, p.burn_in_mode,
                                               p.samples)
        no_edges = roll_out(model, batch, p, none, edges_off=True) if model.decoder_edges else None
        self.metrics.update(batch=batch, forecast=forecast, posterior=posterior, prior=prior,
                            units=units, by_edges=by_edges, prior_per_step=prior_per_step,
                            own_cut=own_cut_inputs(out, batch),
                            cv=cv, futures=futures, no_edges=no_edges, posterior_probs=out.probs)
        return {"segments": posterior.masked_fill(~present, -1),
                "probs": out.probs.gather(-1, posterior.unsqueeze(-1)).squeeze(-1),
                "prior": prior, "per_step": out.step_logits.argmax(-1)}

    def compute(self) -> dict[str, torch.Tensor]:
        """Every ``test/...`` value that saw data; resets."""
        return self.metrics.compute()


@dataclass(frozen=True)
class ForecastRequest:
    """``mode=predict``'s forecast: ``steps`` after each clip's first ``burn_in`` frames, with
    ``samples`` sampled futures beside it (0: none)."""

    burn_in: int
    steps: int
    samples: int = 0


class PredictPass(nn.Module):
    """What a prediction says about clips without ground truth, and its scores: what each edge type
    means and, with a :class:`ForecastRequest` on inputs that hold the forecast's future, its ADE /
    FDE beside constant velocity's."""

    def __init__(self, num_types: int, horizons: list[int],
                 forecast: ForecastRequest | None) -> None:
        super().__init__()
        self.forecast = forecast
        self.types = TypeProfile(num_types)
        # the protocol's horizons the forecast reaches, else its last step
        scored = [] if forecast is None else [h for h in horizons if h <= forecast.steps] or [forecast.steps]
        self.ade = nn.ModuleDict({k: HorizonDisplacement(scored) for k in ("model", "cv")} if scored
                                 else {})
        self.constant_velocity = ConstantVelocity()

    def update(self, model: RelationalVAE, batch: Batch, units: Units) -> dict[str, object]:
        """:meth:`~dider.models.vae.RelationalVAE.describe` (each [B, E, T-1], ``step_probs`` [B, E,
        T-1, K]), the batch's ``states``, ``mask`` and ``source``, and with a forecast request the
        ``forecast`` [B, steps, N, D] (agents present at the burn-in's last frame carry on) and
        ``forecast_samples`` [B, K, steps, N, D]."""
        x, mask, f, units = batch["states"], batch["mask"], self.forecast, units or data_units(None)
        out: dict[str, object] = {"states": x, "mask": mask, "source": batch.get("source", {})}
        if f is not None:  # first: its sampled edges are the first draws from eval_seed
            out["forecast"] = forecast = model.forecast_after(x, mask, f.burn_in, f.steps)
            if f.samples:
                out["forecast_samples"] = model.forecast_after(x, mask, f.burn_in, f.steps,
                                                               samples=f.samples)
            # the input holds the future: scored as the test pass scores
            if x.shape[1] >= f.burn_in + f.steps:
                cv = model.forecast_after(x, mask, f.burn_in, f.steps, self.constant_velocity)
                target = units(x[:, f.burn_in:f.burn_in + f.steps])
                scored = scored_targets(mask[:, :f.burn_in + f.steps], f.burn_in, "global")
                for name, pred in {"model": forecast, "cv": cv}.items():
                    self.ade[name].update(units(pred), target, scored)
        out |= model.describe(model.infer(batch, hard=True), mask)
        self.types.update(out["segments"], *pair_features(units(x), mask))
        return out

    def reset(self) -> None:
        _reset(self)

    def values(self) -> dict[str, torch.Tensor]:
        """``predict/typeK/...`` and, where a forecast was scored, ``predict/ade/hXX``,
        ``predict/ade_vs_cv/hXX``."""
        out: dict[str, torch.Tensor] = {}
        if self.types.update_count:
            out |= profile_values("predict", self.types)
        if "model" in self.ade and self.ade["model"].update_count:
            out |= displacement_values("predict", self.ade["model"], self.ade["cv"])
        return out


def _reset(module: nn.Module) -> None:
    for metric in module.modules():
        if isinstance(metric, Metric):
            metric.reset()
