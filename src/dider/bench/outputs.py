"""The end-of-run outputs at many agents per window: what a test pass writes after its metrics (the
segment list of every test clip, the explorer's clips, the timeline and trajectory figures), timed
on synthetic outputs of the shapes a scene of ``agents`` agents gives, so a large scene's cost shows
without training."""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import torch

from dider.io import atomic_write_text
from dider.outputs.clips import explore_arrays, split_clips, stack_clips, write_clips_npz
from dider.outputs.export import segments_json
from dider.outputs.viz import timeline_figure, trajectory_figure


def fake_outputs(clips: int, agents: int, steps: int, num_types: int = 2,
                 seed: int = 0) -> dict[str, torch.Tensor]:
    """Stacked test outputs of ``clips`` clips: types in runs (a switch on 5% of steps, a quarter of
    the edges interacting), agents leaving and entering, random-walk positions.

    -> segments/per_step/prior/truth [S, E, T-1] long (-1 absent), probs [S, E, T-1], states [S, T,
    N, 4], mask [S, T, N] bool.
    """
    g = torch.Generator().manual_seed(seed)
    e = agents * (agents - 1)
    switch = torch.rand(clips, e, steps - 1, generator=g) < 0.05
    run = switch.long().cumsum(-1)
    active = torch.rand(clips, e, 1, generator=g) < 0.25
    types = torch.where(active,
                        (run + torch.randint(num_types, (clips, e, 1), generator=g)) % num_types, 0)
    mask = torch.ones(clips, steps, agents, dtype=torch.bool)
    leave = torch.randint(steps // 2, steps + 1, (clips, 1, agents), generator=g)
    mask &= torch.arange(steps)[None, :, None] < leave
    from dider.graph import edge_index

    send, recv = edge_index(agents)
    present = (mask[:, :-1, send] & mask[:, :-1, recv]).transpose(1, 2)  # [S, E, T-1]
    types = types.masked_fill(~present, -1)
    states = torch.randn(clips, steps, agents, 4, generator=g).cumsum(1)
    return {"segments": types, "per_step": types, "prior": types, "truth": types,
            "probs": torch.rand(clips, e, steps - 1, generator=g), "states": states, "mask": mask}


def time_outputs(agents: int, clips: int = 64, steps: int = 50, figures: int = 4,
                 tmpdir: str | Path | None = None) -> dict[str, Any]:
    """Seconds of each end-of-run output at ``agents`` agents per clip: {"segments_json",
    "clips_npz", "timelines", "trajectories", "total"} and the edge count."""
    arrays = fake_outputs(clips, agents, steps)
    seconds: dict[str, float] = {}
    with tempfile.TemporaryDirectory(dir=tmpdir) as out:
        out_dir = Path(out)
        t0 = time.perf_counter()
        # as the export callback holds them at the end of a test
        stacked = stack_clips(split_clips(arrays))
        atomic_write_text(out_dir / "segments.json", json.dumps(segments_json(stacked)))
        seconds["segments_json"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        first = {k: v[:50] for k, v in stacked.items()}
        write_clips_npz(out_dir / "clips.npz", explore_arrays(first, None), {})
        seconds["clips_npz"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        for i in range(figures):
            rows = {k: arrays[k][i] for k in ("truth", "per_step", "segments", "prior")}
            fig = timeline_figure(rows, 2, title=f"clip {i}")
            fig.savefig(out_dir / f"timeline_{i}.png", dpi=100)
            plt.close(fig)
        seconds["timelines"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        for i in range(figures):
            fig = trajectory_figure(arrays["states"][i, ..., :2], arrays["mask"][i],
                                    arrays["segments"][i], 2)
            fig.savefig(out_dir / f"trajectories_{i}.png", dpi=100)
            plt.close(fig)
        seconds["trajectories"] = time.perf_counter() - t0
    seconds["total"] = sum(seconds.values())
    return {"seconds": seconds, "edges": agents * (agents - 1), "clips": clips, "steps": steps,
            "figures": figures}
