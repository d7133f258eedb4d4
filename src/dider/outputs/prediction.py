"""``mode=predict``: what a trained model says about every clip of new data, written into the run
folder.

``predictions/`` holds
- ``segments.csv`` (and ``segments.parquet`` when pyarrow is installed): one row per (clip, sender,
  receiver, segment) with its steps, the input's frame numbers and ids, type and probability
  (:func:`dider.outputs.clips.segment_frame`);
- ``clips.npz``: the arrays behind it (``segments``, ``probs``, ``per_step``, ``prior`` [S, E, T-1],
  ``step_probs`` [S, E, T-1, K] per-step edge-type probabilities, ``positions`` [S, T, N, 2] and
  ``mask`` [S, T, N] in the input's units, source ids), read by
  ``python -m dider.analysis.explore``;
- with ``predict.forecast_steps``: ``forecast.csv`` (clip, agent, step, x, y) and ``forecast`` [S,
  P, N, 2] in ``clips.npz``, rolled out from each clip's first ``predict.burn_in`` frames; where the
  clips hold the forecast's future, ``forecast_scores.json``: its ADE / FDE in data units beside
  constant velocity's on the same clips and agents, and their ratio (``predict/ade_vs_cv/hXX``);
- ``types.csv``: what each edge type means, one row per type (:mod:`dider.evaluation.type_meaning`):
  its share of the present edge-steps and the mean distance, closing speed, relative heading and
  receiver acceleration (data units) while it holds (``distance``...) and over the other edge-steps
  (``others_distance``...).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import pandas as pd
import torch
from lightning.pytorch.callbacks import BasePredictionWriter
from lightning.pytorch.utilities.exceptions import SIGTERMException

from dider.evaluation.type_meaning import degenerate_types, profile_rows
from dider.io import atomic_write_bytes, atomic_write_text
from dider.outputs.clips import (
    explore_arrays,
    explore_extras,
    gather_in_order,
    named,
    segment_frame,
    split_clips,
    stack_clips,
    write_clips_npz,
    write_table,
)

log = logging.getLogger(__name__)


def forecast_frame(arrays: Mapping[str, torch.Tensor], burn_in: int, frame_step: int = 1,
                   names: Mapping[str, Sequence[str]] | None = None) -> pd.DataFrame:
    """The forecast as a long table: one row per (clip, agent, predicted step) of an agent that
    carries on; with ``forecast_samples`` [S, K, P, N, 2] also the sampled futures, a ``sample``
    column telling them apart (0: the forecast, 1..K: the samples).

    arrays: ``forecast`` [S, P, N, 2] in input units, ``mask`` [S, T, N], optional ``clip`` [S],
    ``scene`` [S], ``agent`` [S, N], ``frame`` [S]; names: key -> names of string ids (as in
    ``segments.csv``). The first predicted step is the clip's frame ``burn_in``."""
    names = names or {}
    if "forecast_samples" in arrays:  # sample 0: the forecast; 1..K: the sampled futures
        # [S, 1+K, P, N, 2]
        futures = torch.cat([arrays["forecast"].unsqueeze(1), arrays["forecast_samples"]], 1)
        frames = [forecast_frame({**{k: v for k, v in arrays.items() if k != "forecast_samples"},
                                  "forecast": futures[:, k]}, burn_in, frame_step, names)
                  .assign(sample=k)
                  for k in range(futures.shape[1])]  # a few samples: one table each, then one sort
        return pd.concat(frames).sort_values(["clip", "sample", "agent", "step"], kind="stable",
                                             ignore_index=True)
    pred = arrays["forecast"]
    s, p, n, _ = pred.shape
    alive = arrays["mask"][:, burn_in - 1]  # [S, N]
    clip_i, step, agent = torch.nonzero(alive[:, None, :].expand(s, p, n), as_tuple=True)
    table: dict[str, Any] = {"clip": (arrays["clip"][clip_i] if "clip" in arrays else clip_i)
                             .numpy()}
    if "scene" in arrays:
        table["scene"] = named(arrays["scene"][clip_i], names.get("scene"))
    table["agent"] = agent.numpy()
    if "agent" in arrays:
        table["agent_id"] = named(arrays["agent"][clip_i, agent], names.get("agent"))
    table["step"] = (burn_in + step).numpy()
    if "frame" in arrays:
        table["frame"] = (arrays["frame"][clip_i] + (burn_in + step) * frame_step).numpy()
    xy = pred[clip_i, step, agent]
    table["x"], table["y"] = xy[:, 0].numpy(), xy[:, 1].numpy()
    return pd.DataFrame(table)


class PredictProgress(L.Callback):
    """A line per ``every_s`` seconds of prediction (clips done, rate, time left) through logging,
    so it shows in a redirected log too; and a SIGTERM stops the prediction at the next batch
    (Lightning's prediction loop does not look), raising :class:`SIGTERMException`."""

    def __init__(self, every_s: float = 30.0) -> None:
        self.every_s = every_s
        self.started = self.last = 0.0

    def on_predict_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.started = self.last = time.monotonic()

    def on_predict_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any,
                             batch: Any, batch_idx: int, dataloader_idx: int = 0) -> None:
        if trainer.received_sigterm:
            raise SIGTERMException
        now = time.monotonic()
        if now - self.last < self.every_s or not trainer.is_global_zero:
            return
        self.last = now
        total = trainer.num_predict_batches[dataloader_idx]
        done, spent = batch_idx + 1, now - self.started
        left = spent / done * (total - done)
        log.info("predict: batch %d of %d (%.0f%%), %.0f s, about %.0f s left", done, total,
                 100 * done / total, spent, left)


class PredictionWriter(BasePredictionWriter):
    """Collects ``predict_step``'s per-clip outputs batch by batch and, on rank 0 after the last
    batch, writes ``output_dir`` (module docstring). Under DDP each rank predicts clips r, r + W,
    ... (the data modules' unrepeated sampler); rank 0 puts them back in input order."""

    def __init__(self, output_dir: str | Path, burn_in: int | None = None) -> None:
        super().__init__(write_interval="batch")
        self.output_dir, self.burn_in = Path(output_dir), burn_in
        self.clips: list[dict[str, torch.Tensor]] = []
        self.written: list[Path] = []
        # the forecast against constant velocity, where the input has its future
        self.scores: dict[str, float] = {}

    def on_predict_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.clips = []

    def write_on_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, prediction: Any,
                           batch_indices: Any, batch: Any, batch_idx: int,
                           dataloader_idx: int = 0) -> None:
        self.clips += split_clips(prediction)

    def on_predict_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.clips = gather_in_order(trainer, self.clips)
        # every rank: its metrics reduce over ranks
        scores = getattr(pl_module, "prediction_scores", dict)()
        self.scores = {k: float(v) for k, v in scores.items()}
        if not trainer.is_global_zero or not self.clips:
            return
        dm = getattr(trainer, "datamodule", None)
        frame_step, names = getattr(dm, "frame_step", 1), getattr(dm, "source_names", {})
        arrays = explore_arrays(stack_clips(self.clips), dm)
        out = self.output_dir
        self.written = write_table(segment_frame(arrays, frame_step, names), out / "segments.csv")
        extra = explore_extras(pl_module, dm, "predict", arrays, self.scores)
        if "forecast" in arrays and self.burn_in is not None:
            extra["forecast_start"] = np.array(self.burn_in)  # the explorer draws it from there
        write_clips_npz(out / "clips.npz", arrays, extra)
        self.written.append(out / "clips.npz")
        if "forecast" in arrays and self.burn_in is not None:
            table = forecast_frame(arrays, self.burn_in, frame_step, names)
            atomic_write_bytes(out / "forecast.csv", table.to_csv(index=False).encode())
            self.written.append(out / "forecast.csv")
        forecast = {k: v for k, v in self.scores.items() if "/type" not in k}
        if forecast:
            # NaN: no agent got there
            strict = {k: v if math.isfinite(v) else None for k, v in forecast.items()}
            atomic_write_text(out / "forecast_scores.json", json.dumps(strict, indent=2))
            self.written.append(out / "forecast_scores.json")
        if rows := profile_rows(self.scores, "predict"):
            self.written += write_table(pd.DataFrame(rows), out / "types.csv")
            if warning := degenerate_types(self.scores, "predict"):
                log.warning(warning)
        self.clips = []
