"""A callback for timing a real job on a GPU (``+callbacks.step_timer._target_=step_timer.StepTimer``): the wall time
of the training steps after the first ``skip`` (the device synchronised at both ends of that window, not per step,
so the host may run ahead as it does in a job), of each validation and of the test, written as JSON to ``path``."""

from __future__ import annotations

import json
import time

import lightning as L
import torch


class StepTimer(L.Callback):
    def __init__(self, path: str, skip: int = 20) -> None:
        self.path, self.skip = path, skip
        self.record: dict = {"val_s": []}
        self.t0 = self.started = 0.0
        self.steps = 0

    @staticmethod
    def _now() -> float:
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        return time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if batch_idx + 1 == self.skip:
            self.t0, self.steps = self._now(), 0
        elif batch_idx + 1 > self.skip:
            self.steps += 1

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        if self.steps:
            self.record |= {"steps_timed": self.steps, "step_s": (self._now() - self.t0) / self.steps}
        graphed = pl_module.graphed
        self.record["graph_replays"] = graphed.graph.replays if graphed is not None else 0
        self._write()

    def on_validation_start(self, trainer, pl_module) -> None:
        self.started = self._now()

    def on_validation_end(self, trainer, pl_module) -> None:
        self.record["val_s"].append(self._now() - self.started)

    def on_test_start(self, trainer, pl_module) -> None:
        self.started = self._now()

    def on_test_end(self, trainer, pl_module) -> None:
        self.record["test_s"] = self._now() - self.started
        self._write()

    def _write(self) -> None:
        with open(self.path, "w") as f:
            json.dump(self.record, f, indent=1)
