"""The Lightning shell around :class:`~dider.models.vae.RelationalVAE`: the optimiser, the schedules' clock,
the forecast protocol of validation and test, and logging. The maths lives in the plain model.

Built from the model config alone; :meth:`RelationalVAEModule.from_checkpoint` rebuilds it from a checkpoint's.
Shapes: B batch, T frames, N agents, D features, E edges, K edge types, P predicted steps.
"""

from __future__ import annotations

import inspect
import logging
from collections.abc import Callable, Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch
from omegaconf import DictConfig
from torchmetrics import Metric

from dider import __version__
from dider.data.batch import Batch
from dider.data.common import data_description
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
from dider.evaluation.type_meaning import TypeProfile, degenerate_types, pair_features, profile_values
from dider.graph import edge_mask
from dider.models.baselines import ConstantVelocity
from dider.models.checkpoint_format import check_format, network_config, read, stamp
from dider.models.plugins import Progress
from dider.models.vae import Inference, plain_config
from dider.protocol import agent_horizons, scored_targets
from dider.targets import build, check, named_targets
from dider.training import callbacks as cb
from dider.training.first_batch import fit_to_a_training_batch
from dider.training.graphed import GraphedSteps, wanted
from dider.training.step_metrics import EpochMeans
from dider.validation import require

log = logging.getLogger(__name__)


class RelationalVAEModule(L.LightningModule):
    def __init__(
        self,
        net: Mapping[str, Any] | None = None,
        optimizer: Mapping[str, Any] | None = None,
        scheduler: Mapping[str, Any] | None = None,
        burn_in: int = 5,
        horizons: Sequence[int] = (1, 15, 25),
        burn_in_mode: str | None = None,
        eval_seed: int = 0,
        check_finite: bool = True,
        samples: int = 0,
        miss_threshold: float | None = None,
        *,
        trust: Collection[str] | None = None,
    ) -> None:
        """net: the network's config (the ``net`` node of ``conf/model``), built as ``self.model``. optimizer,
        scheduler: configs of partial factories (``_partial_: true``). burn_in, horizons, burn_in_mode: the forecast
        protocol (``conf/model`` interpolates the ``protocol`` node; None: ``global``). eval_seed: validation and
        test draw from it. check_finite: stop on a NaN/inf loss term or gradient. samples, miss_threshold: the
        sampled futures each test pass scores (:mod:`dider.evaluation.sampled`). trust (not a hyper-parameter):
        None when the config is the caller's own (every class it names may be built), else the user's classes a
        file's config may build beside dider's (:mod:`dider.targets`)."""
        super().__init__()
        if net is None:
            raise TypeError("RelationalVAEModule: net, the network's config, is required")
        net = plain_config(net)
        require({"model.burn_in_mode": burn_in_mode, "model.check_finite": check_finite, "model.samples": samples,
                 "model.miss_threshold": miss_threshold})
        self.save_hyperparameters(logger=False, ignore=["trust"])
        self.trust = named_targets([net, optimizer, scheduler]) if trust is None else frozenset(trust)
        self.model = build(net, "network", "model config", "model.net", self.trust)
        self.val_mse = HorizonMSE(horizons)
        # the forecast in data units beside constant velocity's, so that a recipe is chosen on validation
        self.val_ade = torch.nn.ModuleDict({k: HorizonDisplacement(horizons) for k in ("model", "cv")})
        self.val_acc = EdgeAccuracy()
        self.val_cut = OwnCut(tolerance=2)
        self.test_metrics = TestMetrics(horizons, self.model.num_types, samples, miss_threshold)
        self.constant_velocity = ConstantVelocity()  # no parameters: scored beside the model at test
        # mode=predict's optional forecast, (burn_in, steps) from each clip's first frames (not a hyper-parameter)
        self.predict_forecast: tuple[int, int] | None = None
        self.predict_samples = 0  # with predict_forecast: that many sampled futures of each clip too
        self.predict_scores: torch.nn.ModuleDict | None = None  # set at the start of each prediction
        # Training steps replayed from one CUDA graph (``cuda_graph``; dider.training.graphed): how a step runs
        self.cuda_graph: bool | str = False
        self._graphed: GraphedSteps | None = None
        self.epoch_means = EpochMeans()  # the training epoch's logged values, kept on the device

    @classmethod
    def from_config(cls, cfg: DictConfig | Mapping[str, Any]) -> RelationalVAEModule:
        """From a model config (``cfg.model``: the module's settings and the network's ``net`` node)."""
        node = plain_config(cfg)  # the module's settings: its arguments (the preflight refuses any other key)
        return cls(net=network_config(node), **{k: node[k] for k in cls.setting_names() if k != "net" and k in node})

    @classmethod
    def setting_names(cls) -> list[str]:
        """The module's settings, the keys of a model config's top level: its constructor's arguments."""
        return [k for k in inspect.signature(cls.__init__).parameters if k not in ("self", "trust")]

    @classmethod
    def from_checkpoint(cls, path: str | Path, trust: Collection[str] = (), **settings: Any) -> RelationalVAEModule:
        """The module a training checkpoint holds, with its weights, its hyper-parameters checked whole first
        (:mod:`dider.targets`); ``settings`` replace the checkpoint's (``burn_in_mode="per_agent"``)."""
        ckpt = read(path)
        hparams = {**ckpt["hyper_parameters"], **settings}
        check(hparams, "module", path, "hyper_parameters", trust)
        module = cls(**{k: v for k, v in hparams.items() if k in cls.setting_names()}, trust=trust)
        module.on_load_checkpoint(ckpt)
        module.load_state_dict(ckpt["state_dict"])
        return module

    @classmethod
    def load_from_checkpoint(cls, checkpoint_path: Any, map_location: Any = None, strict: bool | None = None,
                             **kwargs: Any) -> RelationalVAEModule:
        """Lightning's entry, read as :meth:`from_checkpoint` reads (``hparams_file`` is not taken: the module is
        built from the checkpoint's own, checked, hyper-parameters; ``strict`` is always true)."""
        if kwargs.pop("hparams_file", None) is not None or strict is False:
            raise TypeError("RelationalVAEModule.load_from_checkpoint: hparams_file and strict=False are not taken")
        return cls.from_checkpoint(checkpoint_path, **kwargs).to(map_location or "cpu")

    @property
    def burn_in_mode(self) -> str:
        """The forecast protocol's burn-in mode (:mod:`dider.protocol`)."""
        return self.hparams.burn_in_mode or "global"

    def progress(self) -> Progress:
        """The schedules' clock: optimiser steps taken, out of the run's total (when the Trainer knows it)."""
        total = self._trainer.estimated_stepping_batches if self._trainer is not None else None
        return Progress(self.global_step, int(total) if total and total != float("inf") else None)

    @property
    def automatic_optimization(self) -> bool:
        """Lightning's own optimisation loop, unless the steps are graphed (then the module takes the step)."""
        return not wanted(self.cuda_graph, self._trainer)

    def _infer(self, batch: Batch, hard: bool) -> Inference:
        # the step count only: the run's length, asked in a test, sets up the training loader (a random draw)
        return self.model.infer(batch, hard, Progress(self.global_step))

    def loss_terms(self, batch: Batch, hard: bool = False) -> dict[str, torch.Tensor]:
        """The loss terms of a batch at the current progress (the NaN/inf guard replays steps with it)."""
        return self.model.loss(self._infer(batch, hard), self.progress())

    def forward(self, x: torch.Tensor, mask: torch.Tensor, burn_in: int, num_pred: int) -> torch.Tensor:
        """The forecast [B, P, N, D] of the plain model under this module's burn-in mode."""
        return self.model(x, mask, burn_in, num_pred, self.burn_in_mode)

    def on_fit_start(self) -> None:
        """On a GPU, the data module's in-memory clips move there (``to_device``); then what is fitted to a training
        batch (:func:`~dider.training.first_batch.fit_to_a_training_batch`)."""
        dm = getattr(self.trainer, "datamodule", None)
        if self.device.type == "cuda" and hasattr(dm, "to_device"):  # batches made on the GPU, not copied there
            dm.to_device(self.device)
        fit_to_a_training_batch(self.model, self.trainer, dm, self.device)

    def monitorable(self) -> set[str]:
        """Every metric a checkpoint or early-stopping callback may monitor: what validation logs (each loss term,
        ``val/nelbo``, ``val/select``, the forecast per horizon, the segments and, on data with ground truth, the
        edge recalls) and training's epoch means. Some are logged only where the data allow (a horizon no agent
        reaches, an own cut without a boundary); the set holds every name that can be."""
        hs = [f"h{int(h):02d}" for h in self.hparams.horizons]
        terms = [*self.model.objective.names(), "loss", "nelbo"]
        segments = ["segments_per_edge", "steps_per_segment", "sigma"]
        val = {*(f"val/{k}" for k in [*terms, "select"]), *(f"val/segments/{k}" for k in segments),
               "val/segments/on_switch", "val/segments/boundary_f1", "val/segments/per_constant_edge",
               "val/edge_acc/posterior/none", "val/edge_acc/posterior/interaction"}
        val |= {f"val/{kind}/{h}" for kind in ("mse", "ade", "fde", "cv/ade", "cv/fde", "ade_vs_cv") for h in hs}
        train = {*(f"train/{k}_{when}" for k in terms for when in ("step", "epoch")),
                 *(f"train/segments/{k}" for k in segments), *(f"train/schedule/{k}" for k in self.model.schedule())}
        return val | train | {"loss"}

    def configure_callbacks(self) -> list[L.Callback]:
        guard = [cb.FiniteGuard()] if self.hparams.check_finite else []
        checks = [cb.ProtocolFits(), cb.EdgeLabelsFit(), cb.EvalRandomState(self.hparams.eval_seed), *guard]
        return [*checks, cb.ResumeMidEpoch(), cb.SaveOnTerminate()]

    def _log_segments(self, stage: str, out: Inference, batch: Batch) -> None:
        """How the duration plugin cuts the edges (segments per edge, their length, the latents' spread)."""
        present = edge_mask(batch["mask"][:, :-1]).any(1)  # [B, E]
        stats = {f"{stage}/segments/{k}": v for k, v in out.seg.stats(present).items()}
        self.log_dict(stats, on_step=False, on_epoch=True, batch_size=batch["states"].shape[0], sync_dist=True)

    def train_values(self, batch: Batch, progress: Progress) -> dict[str, torch.Tensor]:
        """A training pass at ``progress`` (the annealed schedules, tau too): the loss terms and ``segments/<stat>``
        (how the duration plugin cut the batch's edges)."""
        out = self.model.infer(batch, False, progress)
        present = edge_mask(batch["mask"][:, :-1]).any(1)  # [B, E]
        return self.model.loss(out, progress) | {f"segments/{k}": v for k, v in out.seg.stats(present).items()}

    def training_step(self, batch: Batch, batch_idx: int) -> dict[str, torch.Tensor]:
        progress = self.progress()
        schedule = self.model.schedule(progress)
        bs = batch["states"].shape[0]
        if not self.automatic_optimization:  # one CUDA graph's replay, then the optimiser step
            self._graphed = self._graphed or GraphedSteps(self)
            values = self._graphed.step(batch, schedule)
        else:
            values = self.train_values(batch, progress)
        terms = {k: v for k, v in values.items() if not k.startswith("segments/")}
        if self._trainer is not None and self._trainer.progress_bar_callback is not None:  # shown: read each step
            self.log("loss", terms["loss"], prog_bar=True, logger=False, batch_size=bs)
        self.epoch_means.add({**{f"train/{k}": v for k, v in values.items()},
                               **{f"train/schedule/{k}": float(v) for k, v in schedule.items()}}, bs)
        if self._writes_logs():  # the step's own values, on the steps the trainer writes (log_every_n_steps)
            self.log_dict({f"train/{k}_step": v for k, v in terms.items()}, on_step=True, on_epoch=False,
                          batch_size=bs)
        return {k: v if k == "loss" else v.detach() for k, v in terms.items()}

    def _writes_logs(self) -> bool:
        connector = getattr(self._trainer, "_logger_connector", None)
        return bool(getattr(connector, "should_update_logs", True))

    def _log_epoch_means(self) -> None:
        """train/<term>_epoch, train/segments/*, train/schedule/*: the epoch's means (kept by :class:`EpochMeans`)."""
        terms = {f"train/{k}" for k in (*self.model.objective.names(), "loss", "nelbo")}
        means = {f"{k}_epoch" if k in terms else k: v for k, v in self.epoch_means.means().items()}
        if means:
            self.log_dict(means, on_step=False, on_epoch=True, sync_dist=True, batch_size=1)  # means already
        self.epoch_means.reset()

    def on_train_batch_end(self, outputs: Any, batch: Batch, batch_idx: int) -> None:
        if batch_idx + 1 >= self.trainer.num_training_batches:  # before validation and the epoch's callbacks read it
            self._log_epoch_means()

    def on_train_epoch_end(self) -> None:
        self._log_epoch_means()  # an epoch stopped before its last batch (nothing left after the last)
        if not self.automatic_optimization and (scheduler := self.lr_schedulers()) is not None:
            scheduler.step()  # Lightning steps epoch schedulers itself only in its own loop

    def _forecast(self, batch: Batch, edges: torch.Tensor | None = None, decoder: torch.nn.Module | None = None,
                  edges_off: bool = False) -> Forecast:
        """Roll out over the whole clip after the burn-in (each agent's own burn-in in ``per_agent`` mode,
        where each target carries its own horizon; frame p is horizon p + 1 in ``global`` mode), with the
        model's own edges or given ones (edges [B, E, T-1]) or none at all (``edges_off``), with the model's decoder or
        another one."""
        x, mask, b = batch["states"], batch["mask"], self.hparams.burn_in
        mode = self.burn_in_mode
        pred, types = self.model.rollout(x, mask, b, x.shape[1] - b, mode, edges, decoder, edges_off=edges_off)
        horizon = agent_horizons(mask, b)[:, b:] if mode == "per_agent" else None
        return Forecast(pred, x[:, b:], scored_targets(mask, b, mode), types, horizon)

    def validation_step(self, batch: Batch, batch_idx: int) -> None:
        out = self._infer(batch, hard=True)
        progress = self.progress()
        terms = self.model.loss(out, progress)
        # val/select: the negative ELBO once the KL weight is 1; inf in the warm-up (the posterior not yet held)
        warm = self.model.schedule(progress)["kl_weight"] >= 1.0
        terms["select"] = terms["nelbo"] if warm else torch.full_like(terms["nelbo"], float("inf"))
        self.log_dict({f"val/{k}": v for k, v in terms.items()}, batch_size=batch["states"].shape[0], sync_dist=True)
        f = self._forecast(batch)
        self.val_mse.update(f.pred, f.target, f.mask, f.horizon)
        cv = self._forecast(batch, torch.zeros_like(out.posterior_types()), self.constant_velocity)
        units = self._data_units()
        for name, pred in {"model": f.pred, "cv": cv.pred}.items():
            self.val_ade[name].update(units(pred), units(f.target), f.mask, f.horizon)
        self._log_segments("val", out, batch)
        if (cut := own_cut_inputs(out, batch)) is not None:
            self.val_cut.update(**cut)
        if "edges" in batch:
            present = edge_mask(batch["mask"][:, :-1])  # [B, T-1, E]
            self.val_acc.update(out.posterior_types().transpose(1, 2), batch["edges"], present)

    def on_validation_epoch_end(self) -> None:
        self.log_dict(horizon_values("val/mse", self.val_mse))
        self.log_dict(displacement_values("val", self.val_ade["model"], self.val_ade["cv"]))
        self.val_mse.reset()
        for metric in self.val_ade.values():
            metric.reset()
        if self.val_acc.update_count:
            self.log_dict(edge_acc_values("val/edge_acc/posterior", self.val_acc))
            self.val_acc.reset()
        if self.val_cut.update_count:
            self.log_dict(own_cut_values("val/segments", self.val_cut))
            self.val_cut.reset()

    def test_step(self, batch: Batch, batch_idx: int) -> dict[str, torch.Tensor]:
        """Scores the batch and returns its per-clip outputs for the export and figure callbacks:
        ``segments`` (posterior types, -1 where the edge is absent), ``probs`` (their probability),
        ``prior`` (online types) and ``per_step`` (per-step posterior types), each [B, E, T-1]."""
        out = self._infer(batch, hard=True)
        terms = self.model.loss(out, self.progress())
        bs = batch["states"].shape[0]
        self.log_dict({f"test/{k}": v for k, v in terms.items() if k != "loss"}, batch_size=bs, sync_dist=True)
        # the model's own cut (its slots), beside the type switches test/segments_per_edge counts (runs of one type)
        self._log_segments("test", out, batch)
        present = edge_mask(batch["mask"][:, :-1]).transpose(1, 2)  # [B, E, T-1]
        posterior, prior = out.posterior_types(), self.model.online_types(out.h_fwd, present)
        normalizer = getattr(getattr(self.trainer, "datamodule", None), "normalizer", None)
        forecast = self._forecast(batch)
        by_edges = {"posterior": self._forecast(batch, posterior)}
        if "edges" in batch:
            by_edges["oracle"] = self._forecast(batch, batch["edges"].transpose(1, 2))
        prior_per_step = self.model.prior(out.h_fwd).argmax(-1)
        cv = self._forecast(batch, torch.zeros_like(posterior), self.constant_velocity)
        futures = None
        if self.hparams.samples:  # drawn aside: the other metrics' draws are those of a test pass without them
            b = self.hparams.burn_in
            with torch.random.fork_rng(devices=[self.device] if self.device.type == "cuda" else []):
                futures = self.model.sample_futures(batch["states"], batch["mask"], b, batch["states"].shape[1] - b,
                                                    self.burn_in_mode, self.hparams.samples)
        no_edges = (self._forecast(batch, torch.zeros_like(posterior), edges_off=True) if self.model.decoder_edges
                    else None)
        self.test_metrics.update(batch, forecast, posterior, prior, normalizer, by_edges, prior_per_step,
                                 own_cut_inputs(out, batch), cv, futures, no_edges, out.probs)
        absent = ~present
        return {"segments": posterior.masked_fill(absent, -1),
                "probs": out.probs.gather(-1, posterior.unsqueeze(-1)).squeeze(-1),
                "prior": prior, "per_step": out.step_logits.argmax(-1)}

    def on_test_epoch_end(self) -> None:
        values = self.test_metrics.compute()
        self.test_values = {k: float(v) for k, v in values.items()}  # float64: the log's float32 ends at 3.4e38
        self.log_dict(values)
        if self.trainer.is_global_zero and (warning := degenerate_types(self.test_values, "test")):
            log.warning(warning)

    def predict_step(self, batch: Batch, batch_idx: int) -> dict[str, Any]:
        """What the model says about clips without ground truth: :meth:`RelationalVAE.describe` (each [B, E, T-1],
        ``step_probs`` [B, E, T-1, K]), the batch's ``states``, ``mask`` and ``source``, and with ``predict_forecast
        = (burn_in, steps)`` the ``forecast`` [B, steps, N, D] from each clip's first burn_in frames (agents present
        at the burn-in's last frame carry on), with ``predict_samples`` K ``forecast_samples`` [B, K, steps, N, D]."""
        x, mask = batch["states"], batch["mask"]
        out: dict[str, Any] = {"states": x, "mask": mask, "source": batch.get("source", {})}
        if self.predict_forecast is not None:  # first: its sampled edges are the first draws from eval_seed
            out["forecast"] = self.model.forecast_after(x, mask, *self.predict_forecast)
            if self.predict_samples:
                out["forecast_samples"] = self.model.forecast_after(x, mask, *self.predict_forecast,
                                                                    samples=self.predict_samples)
            self._score_forecast(x, mask, out["forecast"])
        out |= self.model.describe(self.model.infer(batch, hard=True), mask)
        self.predict_scores["types"].update(out["segments"], *pair_features(self._data_units()(x), mask))
        return out

    def _data_units(self) -> Callable[[torch.Tensor], torch.Tensor]:
        return data_units(getattr(getattr(self.trainer, "datamodule", None), "normalizer", None))

    def on_predict_epoch_start(self) -> None:
        scores: dict[str, Metric] = {"types": TypeProfile(self.model.num_types)}
        if self.predict_forecast is not None:
            steps = self.predict_forecast[1]
            horizons = [h for h in self.hparams.horizons if h <= steps] or [steps]
            scores |= {k: HorizonDisplacement(horizons) for k in ("model", "cv")}
        self.predict_scores = torch.nn.ModuleDict(scores).to(self.device)

    def _score_forecast(self, x: torch.Tensor, mask: torch.Tensor, forecast: torch.Tensor) -> None:
        """Where the input holds the forecast's future, score the forecast [B, P, N, D] and constant velocity's in
        data units, at the frames of agents present since the burn-in's last frame (as the test pass does)."""
        burn_in, steps = self.predict_forecast
        if x.shape[1] < burn_in + steps:
            return
        cv = self.model.forecast_after(x, mask, burn_in, steps, self.constant_velocity)
        units = self._data_units()
        target = units(x[:, burn_in:burn_in + steps])
        scored = scored_targets(mask[:, :burn_in + steps], burn_in, "global")
        for name, pred in {"model": forecast, "cv": cv}.items():
            self.predict_scores[name].update(units(pred), target, scored)

    def prediction_scores(self) -> dict[str, torch.Tensor]:
        """After ``mode=predict``: what each edge type means (``predict/typeK/...``) and, with a forecast on inputs
        that hold its future, ``predict/ade/hXX``, ``predict/ade_vs_cv/hXX``, ... Every rank calls it."""
        scores, out = self.predict_scores or {}, {}
        if "types" in scores and scores["types"].update_count:
            out |= profile_values("predict", scores["types"])
        if "model" in scores and scores["model"].update_count:
            out |= displacement_values("predict", scores["model"], scores["cv"])
        return out

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # what dider.load needs beside the hyper-parameters: the package version, the data's description and normaliser
        dm = getattr(self._trainer, "datamodule", None) if self._trainer is not None else None
        stamp(checkpoint, version=__version__, data=data_description(dm))

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # A resumed or tested run reads the file through Lightning: only today's format, before its weights load.
        check_format(checkpoint)

    def configure_optimizers(self) -> Any:
        make = build(self.hparams.optimizer or {"_target_": "torch.optim.Adam", "_partial_": True}, "optimizer",
                     "model config", "model.optimizer", self.trust)
        # on a GPU the step count stays on the device (``capturable``): a CUDA graph can hold the update, same maths
        capturable = self.device.type == "cuda" and "capturable" in inspect.signature(make.func).parameters
        opt = make(params=self.parameters(), **({"capturable": True} if capturable else {}))
        if self.hparams.scheduler is None:
            return opt
        make = build(self.hparams.scheduler, "scheduler", "model config", "model.scheduler", self.trust)
        scheduler = make(optimizer=opt)
        # name: the tag LearningRateMonitor logs the rate under (callbacks.lr_monitor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": scheduler, "interval": "epoch", "name": "train/lr"}}
