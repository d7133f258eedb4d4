"""Interpretability outputs: per-edge segment lists for every test clip, written atomically as JSON."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import lightning as L
import torch

from dider.graph import edge_index, num_agents
from dider.io import atomic_write_text


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
    """After testing, writes the posterior segments of every test clip to ``path`` (JSON, atomic).

    Collects the ``segments`` and ``probs`` that ``test_step`` returns per batch; under DDP rank r of W
    tested clips r, r + W, ... (the data modules' unrepeated sampler), so rank 0 puts them back in
    test-set order before writing."""

    def __init__(self, path: str) -> None:
        self.path = Path(path)
        self.batches: list[tuple[torch.Tensor, torch.Tensor]] = []

    def on_test_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.batches = []

    def on_test_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                          batch_idx: int, dataloader_idx: int = 0) -> None:
        if isinstance(outputs, dict) and "segments" in outputs:
            self.batches.append((outputs["segments"].cpu(), outputs["probs"].cpu()))

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        world = trainer.world_size
        if world == 1:
            return
        clips = [(t, p) for tb, pb in self.batches for t, p in zip(tb, pb, strict=True)]
        per_rank: list[Any] | None = [None] * world if trainer.global_rank == 0 else None
        torch.distributed.gather_object(clips, per_rank, dst=0)  # the export runs on rank 0 only
        if trainer.global_rank != 0:
            self.batches = []
            return
        ordered = [per_rank[r][j] for j in range(max(map(len, per_rank))) for r in range(world)
                   if j < len(per_rank[r])]
        self.batches = [(t[None], p[None]) for t, p in ordered]

    def on_test_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.batches and trainer.is_global_zero:
            atomic_write_text(self.path, json.dumps(segments_json(self.batches)))
