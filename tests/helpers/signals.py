"""A callback that stops a real run the way a scheduler does: SIGTERM to its own process at a chosen batch."""

from __future__ import annotations

import os
import signal
from typing import Any

import lightning as L


class TerminateAt(L.Callback):
    """Sends SIGTERM to this process after training batch ``batch`` of epoch ``epoch`` (0-based), once."""

    def __init__(self, epoch: int, batch: int) -> None:
        self.epoch, self.batch, self.sent = epoch, batch, False

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        if not self.sent and trainer.current_epoch == self.epoch and batch_idx == self.batch:
            self.sent = True
            os.kill(os.getpid(), signal.SIGTERM)
