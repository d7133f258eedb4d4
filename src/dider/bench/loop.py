"""A real job's training step: the app's synthetic data module, LightningModule, callbacks, logger
and Lightning's loop, as ``python -m dider.run`` builds them, timed over a run of steps, and the
host synchronisations of the whole step counted (the model, the loss, the backward, the optimiser
and all the loop does around them: logging, the progress of the schedules, the guards). A bare step
(:func:`dider.bench.steps.model_case`) leaves the loop out."""

from __future__ import annotations

import tempfile
import time
from typing import Any

import lightning as L
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from lightning.pytorch.loggers import CSVLogger

from dider.bench.cases import Case
from dider.bench.syncs import HostSyncs
from dider.training.module import RelationalVAEModule


class StepClock(L.Callback):
    """After ``warmup`` training steps, the wall time of the next ``timed`` steps (the device
    synchronised at both ends), then the host synchronisations of the ``counted`` steps after those,
    from each step's start to the next one's (counting slows them: they are not timed)."""

    def __init__(self, warmup: int, timed: int, counted: int) -> None:
        self.warmup, self.timed, self.counted = warmup, timed, counted
        self.started = self.seconds = 0.0
        self.syncs = HostSyncs()
        self.counting = False

    def _sync(self, module: L.LightningModule) -> None:
        if module.device.type == "cuda":
            torch.cuda.synchronize(module.device)

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any,
                             batch_idx: int) -> None:
        if batch_idx == self.warmup:
            self._sync(pl_module)
            self.started = time.perf_counter()
        elif batch_idx == self.warmup + self.timed:
            self._sync(pl_module)
            self.seconds = time.perf_counter() - self.started
            self.syncs.__enter__()
            self.counting = True
        elif batch_idx == self.warmup + self.timed + self.counted and self.counting:
            self._stop()

    def _stop(self) -> None:
        self.syncs.__exit__(None, None, None)
        self.counting = False

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.counting:
            self._stop()


def loop_case(case: Case, device: str) -> tuple[float, dict[str, Any]]:
    """``case.iters`` timed steps of a real job at batch ``case.batch`` on the synthetic set (the
    case's overrides), after ``case.warmup``; then 3 steps counted. -> (seconds a step,
    {host_syncs_per_step, sync_sites})."""
    counted = 3
    steps = case.warmup + case.iters + counted + 1
    with tempfile.TemporaryDirectory() as tmp:
        overrides = [*case.overrides, f"data.num_train={case.batch * steps}", "data.num_val=16",
                     "data.num_test=16", f"data.loader.batch_size={case.batch}",
                     f"data.cache_dir={tmp}", f"output_dir={tmp}"]
        with initialize_config_module(version_base="1.3", config_module="dider.conf"):
            cfg = compose(config_name="config", overrides=overrides)
        torch.manual_seed(0)
        datamodule = instantiate(cfg.data, _convert_="all")
        module = RelationalVAEModule.from_config(cfg.model, cuda_graph=cfg.cuda_graph)
        clock = StepClock(case.warmup, case.iters, counted)
        trainer = L.Trainer(max_epochs=1, accelerator="gpu" if device == "cuda" else "cpu",
                            devices=1, limit_val_batches=0, num_sanity_val_steps=0,
                            enable_progress_bar=False, enable_model_summary=False,
                            enable_checkpointing=False, log_every_n_steps=10,
                            logger=CSVLogger(tmp, name="csv"), callbacks=[clock],
                            precision=cfg.trainer.precision if device == "cuda" else "32-true")
        trainer.fit(module, datamodule=datamodule)
    graphed = module.graphed.graph if module.graphed is not None else None
    return clock.seconds / case.iters, {"host_syncs_per_step": clock.syncs.total / counted,
                                        "sync_sites": dict(clock.syncs.where.most_common(8)),
                                        "cuda_graph": cfg.cuda_graph,
                                        "graph_replays": graphed.replays if graphed is not None
                                        else 0}
