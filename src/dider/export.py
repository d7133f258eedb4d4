"""Interpretability outputs: per-edge segment lists for every test clip, written atomically as JSON."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import lightning as L
import torch

from dider.data.cache import atomic_write_text
from dider.graph import edge_index, num_agents


def segment_table(types: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
    """Runs of constant type on every edge of every clip.

    types: [S, E, T] long, probs: [S, E, T] probability of the chosen type ->
    [R, 6] float rows (clip, edge, start, end (exclusive), type, mean probability over the run).
    """
    s, e, t = types.shape
    new_run = torch.ones_like(types, dtype=torch.bool)
    new_run[..., 1:] = types[..., 1:] != types[..., :-1]
    run_id = new_run.flatten().cumsum(0) - 1  # runs never cross an edge: every edge starts a run
    starts = new_run.flatten().nonzero().squeeze(1)
    ends = torch.cat([starts[1:], torch.tensor([types.numel()])])
    prob_sum = torch.zeros(len(starts), dtype=torch.float64).index_add_(0, run_id, probs.flatten().double())
    clip, rest = starts // (e * t), starts % (e * t)
    edge, start = rest // t, rest % t
    return torch.stack([clip.double(), edge.double(), start.double(), (start + ends - starts).double(),
                        types.flatten()[starts].double(), prob_sum / (ends - starts).double()], dim=1)  # fmt: skip


def segments_json(batches: list[tuple[torch.Tensor, torch.Tensor]]) -> dict[str, Any]:
    """The segments of every test clip, in test-set order.

    batches: (types [B, E, T] long with -1 where the edge is absent, probs [B, E, T]) per test batch; E may
    differ between batches (real data: padded to each batch's largest agent count). ->
    {"clips": [{"clip": i, "edges": [{"sender", "receiver", "segments": [{start, end, type, prob}]}]}]}
    listing only edges present at some step, and only the steps where they are present.
    """
    clips: list[dict[str, Any]] = []
    for types, probs in batches:
        b, e, _ = types.shape
        n = num_agents(e)
        send, recv = edge_index(n)
        edges: list[dict[int, list[dict[str, Any]]]] = [{} for _ in range(b)]
        for clip, edge, start, end, typ, prob in segment_table(types, probs).tolist():
            if typ >= 0:  # runs of -1 are steps where the edge does not exist
                row = {"start": int(start), "end": int(end), "type": int(typ), "prob": round(prob, 4)}
                edges[int(clip)].setdefault(int(edge), []).append(row)
        for per_edge in edges:
            clips.append({"clip": len(clips), "edges": [
                {"sender": int(send[k]), "receiver": int(recv[k]), "segments": rows} for k, rows in per_edge.items()]})
    return {"note": "steps are transitions t -> t+1 of the clip; end is exclusive; agents in the data set's order",
            "clips": clips}


class SegmentExport(L.Callback):
    """After testing, writes the posterior segments of every test clip to ``path`` (JSON, atomic)."""

    def __init__(self, path: str) -> None:
        self.path = Path(path)

    def on_test_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        types = getattr(pl_module, "test_types", None)
        if not types or not trainer.is_global_zero:
            return
        blob = segments_json(list(zip(types, pl_module.test_probs, strict=True)))
        atomic_write_text(self.path, json.dumps(blob))
