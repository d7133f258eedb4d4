"""Host time of a real job's logging a training step, on the CPU: the synthetic job of ``python -m dider.run`` with a
tiny network (widths 8, 10 steps a clip) for 64 steps at batch 16, Lightning's ``log_dict`` timed around every call.
Usage (one process per code version; run each several times, alternating):
    PYTHONPATH=<checkout>/src python docs/journal/loop_logging.py [model] [override ...]  -> one JSON line"""

from __future__ import annotations

import json
import sys
import tempfile
import time

import lightning as L
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from lightning.pytorch.loggers import CSVLogger

from dider.training.module import RelationalVAEModule

torch.set_num_threads(1)
spent = {"s": 0.0, "calls": 0}
log_dict = L.LightningModule.log_dict


def timed(self, *args, **kwargs):
    t = time.perf_counter()
    out = log_dict(self, *args, **kwargs)
    spent["s"] += time.perf_counter() - t
    spent["calls"] += 1
    return out


L.LightningModule.log_dict = timed


class Clock(L.Callback):
    def on_train_start(self, trainer, pl_module):
        self.t = time.perf_counter()

    def on_train_end(self, trainer, pl_module):
        self.s = time.perf_counter() - self.t


model = sys.argv[1] if len(sys.argv) > 1 else "dnri"
tmp = tempfile.mkdtemp()
overrides = [f"model={model}", "data.num_train=1024", "data.num_val=16", "data.num_test=16",
             "data.loader.batch_size=16", f"data.cache_dir={tmp}", f"output_dir={tmp}", "model.net.encoder.hidden=8",
             "model.net.encoder.rnn_hidden=8", "model.net.encoder.head_hidden=8", "model.net.decoder.hidden=8",
             "data.source.num_steps=10", "protocol.burn_in=3", "protocol.horizons=[1,5]", *sys.argv[2:]]
with initialize_config_module(version_base="1.3", config_module="dider.conf"):
    cfg = compose(config_name="config", overrides=overrides)
module = RelationalVAEModule.from_config(cfg.model, cuda_graph=cfg.get("cuda_graph", False))
clock = Clock()
trainer = L.Trainer(max_epochs=1, accelerator="cpu", limit_val_batches=0, num_sanity_val_steps=0,
                    enable_progress_bar=False, enable_model_summary=False, enable_checkpointing=False,
                    log_every_n_steps=10, logger=CSVLogger(tmp, name="csv"), callbacks=[clock], precision="32-true")
trainer.fit(module, datamodule=instantiate(cfg.data, _convert_="all"))
steps = trainer.global_step
print(json.dumps({"model": model, "steps": steps, "step_ms": 1e3 * clock.s / steps,
                  "log_dict_ms_per_step": 1e3 * spent["s"] / steps, "log_dict_calls": spent["calls"]}))
