"""Interpretability outputs of a test: per-edge segment lists of every test clip (JSON) and the
arrays behind them for the explorer (``clips.npz``), written atomically."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch

from dider.evaluation.scoring import seeded_forecast
from dider.io import atomic_write_text
from dider.outputs.clips import (
    explore_arrays,
    explore_extras,
    gather_in_order,
    segment_frame,
    split_clips,
    stack_clips,
    write_clips_npz,
)


def segments_json(arrays: Mapping[str, torch.Tensor], frame_step: int = 1,
                  names: Mapping[str, Sequence[str]] | None = None) -> dict[str, Any]:
    """The segments of every test clip, in test-set order.

    arrays: stacked clips (:func:`dider.outputs.clips.stack_clips`): ``segments`` [S, E, T-1] long
    (-1 where the edge is absent), ``probs`` [S, E, T-1], and the source identifiers the data set
    has (``clip``, ``scene``, ``frame``, ``agent``; :mod:`dider.data.common`). -> {"clips":
    [{"clip": i, "source": {...}, "edges": [{"sender", "receiver", ["sender_id", "receiver_id"],
    "segments": [{start, end, type, prob, [start_frame, end_frame]}]}]}]} listing only edges present
    at some step, and only the steps where they are present.
    """
    s = arrays["segments"].shape[0]
    frame = segment_frame({**arrays, "clip": torch.arange(s)}, frame_step, names)
    keys = [k for k in ("sender_id", "receiver_id") if k in frame]
    seg_keys = (["start", "end", "type", "prob"] + [k for k in ("start_frame", "end_frame")
                                                    if k in frame])
    frame = frame.rename(columns={"start_step": "start", "end_step": "end"})
    clips: list[dict[str, Any]] = []
    for i in range(s):
        clip: dict[str, Any] = {"clip": i}
        if source := _source(arrays, i, names or {}):
            clip["source"] = source
        clip["edges"] = []
        clips.append(clip)
    # one pass over the rows, which come grouped by clip and edge (a groupby per edge costs ~100 us
    # a group: minutes for a test set of large scenes)
    current, edge = None, {}
    for row in frame[["clip", "sender", "receiver", *keys, *seg_keys]].to_dict("records"):
        key = int(row["clip"]), int(row["sender"]), int(row["receiver"])
        if key != current:
            current, edge = (
                key, {"sender": key[1], "receiver": key[2]} | {k: _plain(row[k]) for k in keys})
            edge["segments"] = []
            clips[key[0]]["edges"].append(edge)
        edge["segments"].append({k: _plain(row[k]) for k in seg_keys})
    return {"note": "steps are transitions t -> t+1 of the clip; end is exclusive; agents in the "
                    "data set's order; source: where the clip came from in the input (its index, "
                    "scene, frame of step 0, agent ids)",
            "clips": clips}


def _plain(value: Any) -> Any:
    """numpy scalars -> JSON-ready Python values."""
    return value.item() if hasattr(value, "item") else value


def _source(arrays: Mapping[str, torch.Tensor], i: int,
            names: Mapping[str, Sequence[str]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key in ("clip", "scene", "frame", "agent"):
        if key in arrays:
            value = arrays[key][i].tolist()
            if key in names:
                value = ([names[key][v] if v >= 0 else None for v in value]
                         if isinstance(value, list) else names[key][value])
            out[key] = value
    return out


class SegmentExport(L.Callback):
    """After testing, writes the posterior segments of every test clip to ``path`` (JSON, atomic)
    and the first ``explore_clips`` test clips' arrays to ``clips.npz`` beside it (for
    ``python -m dider.analysis.explore``).

    Collects what ``test_step`` returns per batch and the batch's source identifiers; under DDP rank
    0 puts the clips of every rank back in test-set order before writing."""

    def __init__(self, path: str, explore_clips: int = 50) -> None:
        self.path, self.explore_clips = Path(path), explore_clips
        self.clips: list[dict[str, torch.Tensor]] = []

    def on_test_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.clips = []

    def on_test_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any,
                          batch: Any, batch_idx: int, dataloader_idx: int = 0) -> None:
        if not (isinstance(outputs, dict) and "segments" in outputs):
            return
        absent = outputs["segments"] < 0
        keep = {"segments": outputs["segments"], "probs": outputs["probs"],
                "per_step": outputs["per_step"].masked_fill(absent, -1),
                "prior": outputs["prior"].masked_fill(absent, -1),
                "states": batch["states"], "mask": batch["mask"], "source": batch.get("source", {})}
        if "edges" in batch:
            keep["truth"] = batch["edges"].transpose(1, 2).masked_fill(absent, -1)
        self.clips += split_clips(keep)

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.clips = gather_in_order(trainer, self.clips)

    def on_test_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self.clips or not trainer.is_global_zero:
            return
        dm = getattr(trainer, "datamodule", None)
        arrays = stack_clips(self.clips)
        frame_step, names = getattr(dm, "frame_step", 1), getattr(dm, "source_names", {})
        atomic_write_text(self.path, json.dumps(segments_json(arrays, frame_step, names)))
        if self.explore_clips > 0:
            first = {k: v[: self.explore_clips] for k, v in arrays.items()}
            # the test's, logged by now
            scores = {k: float(v) for k, v in trainer.callback_metrics.items()}
            extra = explore_extras(pl_module, dm, "test", first, scores)
            protocol = getattr(pl_module, "protocol", None)
            burn_in = int(protocol.burn_in) if protocol is not None else 0
            if hasattr(pl_module, "model") and 0 < burn_in < first["states"].shape[1]:
                # the explorer draws the forecast from the burn-in against the true paths
                steps = first["states"].shape[1] - burn_in
                first["forecast"] = seeded_forecast(pl_module, first["states"], first["mask"],
                                                    burn_in, steps)
                extra["forecast_start"] = np.array(burn_in)
            write_clips_npz(self.path.parent / "clips.npz", explore_arrays(first, dm), extra)
