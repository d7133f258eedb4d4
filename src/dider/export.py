"""Interpretability outputs: per-edge segment lists for every test clip, written atomically as JSON."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import lightning as L
import torch

from dider.data.cache import atomic_write_text
from dider.graph import edge_index


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


def segments_json(types: torch.Tensor, probs: torch.Tensor, num_agents: int) -> dict[str, Any]:
    """{"edges": [[sender, receiver], ...], "clips": [[ [ {start, end, type, prob}, ...] per edge ] per clip]}."""
    table = segment_table(types, probs).tolist()
    clips: list[list[list[dict[str, Any]]]] = [[[] for _ in range(types.shape[1])] for _ in range(types.shape[0])]
    for clip, edge, start, end, typ, prob in table:
        row = {"start": int(start), "end": int(end), "type": int(typ), "prob": round(prob, 4)}
        clips[int(clip)][int(edge)].append(row)
    send, recv = edge_index(num_agents)
    return {"note": "steps are transitions t -> t+1; end is exclusive",
            "edges": [[int(a), int(b)] for a, b in zip(send, recv, strict=True)], "clips": clips}


class SegmentExport(L.Callback):
    """After testing, writes the posterior segments of every test clip to ``path`` (JSON, atomic)."""

    def __init__(self, path: str) -> None:
        self.path = Path(path)

    def on_test_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        types = getattr(pl_module, "test_types", None)
        if not types or not trainer.is_global_zero:
            return
        # clips of different batches may hold different agent counts (real data): export per batch shape
        if len({t.shape[1] for t in types}) != 1:
            return
        e = types[0].shape[1]
        n = int(round((1 + (1 + 4 * e) ** 0.5) / 2))
        blob = segments_json(torch.cat(types), torch.cat(pl_module.test_probs), n)
        atomic_write_text(self.path, json.dumps(blob))
