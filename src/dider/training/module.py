"""The Lightning shell around :class:`~dider.models.vae.RelationalVAE`: the optimiser, the schedules' clock and
logging. It is handed the built network, the optimiser's and scheduler's factories and the forecast protocol
(:meth:`~RelationalVAEModule.from_config`, :meth:`~RelationalVAEModule.from_checkpoint`); what validation, test and
prediction score lives beside it (:mod:`dider.evaluation.passes`), the maths in the plain model."""

from __future__ import annotations

import inspect
import logging
from collections.abc import Callable, Collection, Mapping
from functools import partial
from pathlib import Path
from typing import Any

import lightning as L
import torch
from omegaconf import DictConfig

from dider import __version__
from dider.data.batch import Batch
from dider.data.description import data_description
from dider.evaluation.passes import ForecastRequest, PredictPass, TestPass, Units, ValidationPass
from dider.evaluation.scoring import data_units
from dider.evaluation.type_meaning import degenerate_types
from dider.graph import edge_mask
from dider.models.checkpoint_format import check_format, read, stamp
from dider.models.plugins import Progress
from dider.models.vae import Inference, RelationalVAE
from dider.settings import ForecastProtocol
from dider.targets import check
from dider.training.building import module_parts
from dider.training.callbacks import every_run
from dider.training.first_batch import fit_to_a_training_batch
from dider.training.graphed import GraphedSteps, wanted
from dider.training.step_metrics import EpochMeans
from dider.validation import require

log = logging.getLogger(__name__)


class RelationalVAEModule(L.LightningModule):
    def __init__(self, net: RelationalVAE, protocol: ForecastProtocol,
                 optimizer: Callable[..., torch.optim.Optimizer] | None = None,
                 scheduler: Callable[..., Any] | None = None, eval_seed: int = 0, check_finite: bool = True, *,
                 cuda_graph: bool | str = False, forecast: ForecastRequest | None = None,
                 config: Mapping[str, Any] | None = None) -> None:
        """optimizer, scheduler: factories (``optimizer(params=...)``, ``scheduler(optimizer=...)``; None: Adam's
        defaults, no schedule). eval_seed: validation and test draw from it. check_finite: stop on a NaN/inf loss
        term or gradient. cuda_graph: :mod:`~dider.training.graphed`. forecast: ``mode=predict``'s. config: the model
        config the parts were built from, which checkpoints keep as the hyper-parameters that rebuild it."""
        super().__init__()
        require({"model.check_finite": check_finite, "model.eval_seed": eval_seed, "cuda_graph": cuda_graph})
        self.save_hyperparameters(dict(config or {}), logger=False)
        self.model, self.protocol = net, protocol
        self.make_optimizer = optimizer or partial(torch.optim.Adam)
        self.make_scheduler = scheduler
        self.eval_seed, self.check_finite, self.cuda_graph = eval_seed, check_finite, cuda_graph
        self.val_pass = ValidationPass(protocol)
        self.test_pass = TestPass(protocol, net.num_types)
        self.predict_pass = PredictPass(net.num_types, list(protocol.horizons), forecast)
        self.graphed: GraphedSteps | None = None  # the graphed steps, once a graphed fit has taken one
        self.epoch_means = EpochMeans()  # the training epoch's logged values, kept on the device
        self.test_values: dict[str, float] = {}  # the last test pass's values, unrounded

    @classmethod
    def from_config(cls, cfg: DictConfig | Mapping[str, Any], trust: Collection[str] | None = None,
                    **run: Any) -> RelationalVAEModule:
        """From a model config (``cfg.model``) by :func:`~dider.training.building.module_parts`; run: the rest."""
        return cls(**module_parts(cfg, trust), **run)

    @classmethod
    def from_checkpoint(cls, path: str | Path, trust: Collection[str] = (), **run: Any) -> RelationalVAEModule:
        """The module a training checkpoint holds, with its weights, its hyper-parameters checked whole first
        (:mod:`dider.targets`; ``trust``: classes of your own it may name). run: ``cuda_graph``, ``forecast``."""
        ckpt = read(path)
        check(ckpt["hyper_parameters"], "module", path, "hyper_parameters", trust)
        module = cls(**module_parts(ckpt["hyper_parameters"], frozenset(trust)), **run)
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
        """The forecast [B, P, N, D] of the plain model under the protocol's burn-in mode."""
        return self.model(x, mask, burn_in, num_pred, self.protocol.burn_in_mode)

    def on_fit_start(self) -> None:
        """On a GPU, the data module's in-memory clips move there; then what is fitted to a training batch."""
        dm = getattr(self.trainer, "datamodule", None)
        if self.device.type == "cuda" and hasattr(dm, "to_device"):  # batches made on the GPU, not copied there
            dm.to_device(self.device)
        fit_to_a_training_batch(self.model, self.trainer, dm, self.device)

    def monitorable(self) -> set[str]:
        """Every metric a checkpoint or early-stopping callback may monitor: what validation logs (each loss term,
        ``val/nelbo``, ``val/select``, the segments, :meth:`ValidationPass.names`) and training's epoch means."""
        terms = [*self.model.objective.names(), "loss", "nelbo"]
        segments = ["segments_per_edge", "steps_per_segment", "sigma"]
        val = {*(f"val/{k}" for k in [*terms, "select"]), *(f"val/segments/{k}" for k in segments)}
        train = {*(f"train/{k}_{when}" for k in terms for when in ("step", "epoch")),
                 *(f"train/segments/{k}" for k in segments), *(f"train/schedule/{k}" for k in self.model.schedule())}
        return val | self.val_pass.names() | train | {"loss"}

    def configure_callbacks(self) -> list[L.Callback]:
        return every_run(self.eval_seed, self.check_finite)

    def _log_segments(self, stage: str, out: Inference, batch: Batch) -> None:
        self.log_dict({f"{stage}/{k}": v for k, v in _segment_stats(out, batch).items()}, on_step=False,
                      on_epoch=True, batch_size=batch["states"].shape[0], sync_dist=True)

    def train_values(self, batch: Batch, progress: Progress) -> dict[str, torch.Tensor]:
        """A training pass at ``progress`` (the annealed schedules, tau too): the loss terms and ``segments/<stat>``."""
        out = self.model.infer(batch, False, progress)
        return self.model.loss(out, progress) | _segment_stats(out, batch)

    def training_step(self, batch: Batch, batch_idx: int) -> dict[str, torch.Tensor]:
        progress = self.progress()
        schedule = self.model.schedule(progress)
        bs = batch["states"].shape[0]
        if not self.automatic_optimization:  # one CUDA graph's replay, then the optimiser step
            self.graphed = self.graphed or GraphedSteps(self)
            values = self.graphed.step(batch, schedule)
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
        return bool(getattr(getattr(self._trainer, "_logger_connector", None), "should_update_logs", True))

    def _log_epoch_means(self) -> None:
        """train/<term>_epoch, train/segments/*, train/schedule/*: the epoch's means (kept by :class:`EpochMeans`)."""
        if means := self.epoch_means.pop({f"train/{k}" for k in (*self.model.objective.names(), "loss", "nelbo")}):
            self.log_dict(means, on_step=False, on_epoch=True, sync_dist=True, batch_size=1)  # means already

    def on_train_batch_end(self, outputs: Any, batch: Batch, batch_idx: int) -> None:
        if batch_idx + 1 >= self.trainer.num_training_batches:  # before validation and the epoch's callbacks read it
            self._log_epoch_means()

    def on_train_epoch_end(self) -> None:
        self._log_epoch_means()  # an epoch stopped before its last batch (nothing left after the last)
        if not self.automatic_optimization and (scheduler := self.lr_schedulers()) is not None:
            scheduler.step()  # Lightning steps epoch schedulers itself only in its own loop

    def validation_step(self, batch: Batch, batch_idx: int) -> None:
        out = self._infer(batch, hard=True)
        progress = self.progress()
        terms = self.model.loss(out, progress)
        # val/select: the negative ELBO once the KL weight is 1; inf in the warm-up (the posterior not yet held)
        warm = self.model.schedule(progress)["kl_weight"] >= 1.0
        terms["select"] = terms["nelbo"] if warm else torch.full_like(terms["nelbo"], float("inf"))
        self.log_dict({f"val/{k}": v for k, v in terms.items()}, batch_size=batch["states"].shape[0], sync_dist=True)
        self._log_segments("val", out, batch)
        self.val_pass.update(self.model, batch, out, self._units())

    def on_validation_epoch_end(self) -> None:
        self.log_dict(self.val_pass.values())

    def test_step(self, batch: Batch, batch_idx: int) -> dict[str, torch.Tensor]:
        """Scores the batch (:class:`~dider.evaluation.passes.TestPass`) -> per-clip outputs for the callbacks."""
        out = self._infer(batch, hard=True)
        terms = self.model.loss(out, self.progress())
        self.log_dict({f"test/{k}": v for k, v in terms.items() if k != "loss"}, batch_size=batch["states"].shape[0],
                      sync_dist=True)
        # the model's own cut (its slots), beside the type switches test/segments_per_edge counts (runs of one type)
        self._log_segments("test", out, batch)
        return self.test_pass.update(self.model, batch, out, self._units())

    def on_test_epoch_end(self) -> None:
        values = self.test_pass.compute()
        self.test_values = {k: float(v) for k, v in values.items()}  # float64: the log's float32 ends at 3.4e38
        self.log_dict(values)
        if self.trainer.is_global_zero and (warning := degenerate_types(self.test_values, "test")):
            log.warning(warning)

    def on_predict_epoch_start(self) -> None:
        self.predict_pass.reset()

    def predict_step(self, batch: Batch, batch_idx: int) -> dict[str, Any]:
        """What the model says about clips without ground truth (:class:`~dider.evaluation.passes.PredictPass`)."""
        return self.predict_pass.update(self.model, batch, self._units())

    def prediction_scores(self) -> dict[str, torch.Tensor]:
        """After ``mode=predict``: what each edge type means (``predict/typeK/...``) and, with a forecast on inputs
        that hold its future, ``predict/ade/hXX``, ``predict/ade_vs_cv/hXX``, ... Every rank calls it."""
        return self.predict_pass.values()

    def _units(self) -> Units:
        """Model states to the data's units, by the data module's normaliser (None without one)."""
        normalizer = getattr(self.trainer.datamodule, "normalizer", None)
        return None if normalizer is None else data_units(normalizer)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # what dider.load needs beside the hyper-parameters: the package version, the data's description and normaliser
        dm = getattr(self._trainer, "datamodule", None) if self._trainer is not None else None
        stamp(checkpoint, version=__version__, data=data_description(dm))

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # A resumed or tested run reads the file through Lightning: only today's format, before its weights load.
        check_format(checkpoint)

    def configure_optimizers(self) -> Any:
        # on a GPU the step count stays on the device (``capturable``): a CUDA graph can hold the update, same maths
        make = self.make_optimizer
        capturable = self.device.type == "cuda" and "capturable" in inspect.signature(make).parameters
        opt = make(params=self.parameters(), **({"capturable": True} if capturable else {}))
        if self.make_scheduler is None:
            return opt
        # name: the tag LearningRateMonitor logs the rate under (callbacks.lr_monitor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": self.make_scheduler(optimizer=opt),
                                                   "interval": "epoch", "name": "train/lr"}}


def _segment_stats(out: Inference, batch: Batch) -> dict[str, torch.Tensor]:
    """How the duration plugin cut a batch's edges: ``segments/<stat>`` (segments per edge, their
    length, the latents' spread) over the edges present at some step."""
    present = edge_mask(batch["mask"][:, :-1]).any(1)  # [B, E]
    return {f"segments/{k}": v for k, v in out.seg.stats(present).items()}
