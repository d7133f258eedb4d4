"""A callback that stops a real run the way a scheduler does: SIGTERM to its own process at a chosen batch."""

from __future__ import annotations

import os
import signal
from typing import Any

import lightning as L


class TerminateAt(L.Callback):
    """Sends ``signal`` (SIGTERM, or SIGINT: Ctrl-C) to this process after batch ``batch`` of epoch ``epoch``
    (0-based) of ``loop``: ``train``, ``val`` (the epoch's validation, not the sanity check) or ``test``, once."""

    def __init__(self, epoch: int, batch: int, loop: str = "train", signal: str = "SIGTERM") -> None:
        self.epoch, self.batch, self.loop, self.signal, self.sent = epoch, batch, loop, signal, False

    def _at(self, trainer: L.Trainer, loop: str, batch_idx: int) -> None:
        if (not self.sent and loop == self.loop and trainer.current_epoch == self.epoch and batch_idx == self.batch
                and not trainer.sanity_checking):
            self.sent = True
            os.kill(os.getpid(), getattr(signal, self.signal))

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        self._at(trainer, "train", batch_idx)

    def on_validation_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                                batch_idx: int, dataloader_idx: int = 0) -> None:
        self._at(trainer, "val", batch_idx)

    def on_test_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                          batch_idx: int, dataloader_idx: int = 0) -> None:
        self._at(trainer, "test", batch_idx)
