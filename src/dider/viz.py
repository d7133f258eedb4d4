"""Figures for TensorBoard and PNG: per-edge interaction timelines (ground truth against inferred) and a
clip's trajectories with its interaction segments drawn between the agents (over the scene image if any)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import lightning as L
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from lightning.pytorch.loggers import MLFlowLogger, TensorBoardLogger, WandbLogger  # noqa: E402

from dider.graph import edge_index, num_agents  # noqa: E402

log = logging.getLogger(__name__)


def timeline_figure(rows: dict[str, torch.Tensor], num_types: int, title: str = "") -> plt.Figure:
    """One panel per edge, one band per source (ground truth, posterior, prior...), coloured by type.

    rows: name -> [E, T] long edge types of one clip.
    """
    names = list(rows)
    e, t = next(iter(rows.values())).shape
    n = num_agents(e)
    send, recv = edge_index(n)
    cmap = plt.get_cmap("tab10", max(num_types, 2))
    fig, axes = plt.subplots(e, 1, figsize=(8, 0.35 * len(names) * e + 1), sharex=True, squeeze=False)
    for k, ax in enumerate(axes[:, 0]):
        img = np.stack([rows[name][k].numpy() for name in names])
        ax.imshow(img, aspect="auto", cmap=cmap, vmin=-0.5, vmax=max(num_types, 2) - 0.5, interpolation="nearest")
        ax.set_yticks(range(len(names)), names, fontsize=7)
        ax.set_ylabel(f"{send[k].item()}→{recv[k].item()}", rotation=0, ha="right", va="center", fontsize=8)
    axes[-1, 0].set_xlabel("transition t → t+1")
    handles = [plt.Rectangle((0, 0), 1, 1, color=cmap(c)) for c in range(num_types)]
    labels = ["0: none"] + [f"{c}" for c in range(1, num_types)]
    fig.legend(handles, labels, loc="upper right", ncol=num_types, fontsize=7, title="edge type", title_fontsize=7)
    fig.suptitle(title, fontsize=9, x=0.02, ha="left")
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    return fig


def trajectory_figure(positions: torch.Tensor, mask: torch.Tensor, types: torch.Tensor, num_types: int,
                      background: tuple[object, tuple[float, float, float, float]] | None = None,
                      title: str = "") -> plt.Figure:
    """A clip's paths with a line from sender to receiver at every step an edge holds an interaction type,
    coloured by that type, so segments show where along the paths they happened.

    positions: [T, N, 2] raw units; mask: [T, N] bool; types: [E, T-1] long (transition t -> t+1 drawn at
    frame t + 1); background: (image, extent) as from ``ClipDataModule.background``.
    """
    t, n = mask.shape
    send, recv = edge_index(n)
    cmap = plt.get_cmap("tab10", max(num_types, 2))
    fig, ax = plt.subplots(figsize=(6, 6))
    if background is not None:
        image, extent = background
        ax.imshow(image, extent=extent, zorder=0)
    pos, present = positions.numpy(), mask.numpy()
    # an edge exists for transition t -> t+1 when both agents are present at t (the model's edge mask) and
    # is drawn at frame t + 1, which needs them there too
    alive = present[:-1] & present[1:]
    both = (alive[:, send.numpy()] & alive[:, recv.numpy()]).T  # [E, T-1]
    e_idx, step = np.nonzero((types.numpy() > 0) & both)
    frame = step + 1
    for c in range(1, num_types):  # one collection per type: few artists however long the clip
        keep = types.numpy()[e_idx, step] == c
        if keep.any():
            a, b = pos[frame[keep], send[e_idx[keep]].numpy()], pos[frame[keep], recv[e_idx[keep]].numpy()]
            ax.plot(np.stack([a[:, 0], b[:, 0]]), np.stack([a[:, 1], b[:, 1]]), color=cmap(c), alpha=0.35,
                    lw=1.0, zorder=1)
    for i in range(n):
        xy = pos[present[:, i], i]
        if len(xy):
            ax.plot(xy[:, 0], xy[:, 1], color="k", lw=1.2, zorder=2)
            ax.scatter(xy[:1, 0], xy[:1, 1], s=12, color="k", zorder=3)
            ax.annotate(str(i), xy[-1], fontsize=7, zorder=3)
    handles = [plt.Line2D([], [], color=cmap(c), lw=2) for c in range(1, num_types)]
    ax.legend(handles, [f"type {c}" for c in range(1, num_types)], fontsize=7, loc="best")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


def _add(trainer: L.Trainer, tag: str, fig: plt.Figure, path: Path) -> None:
    """Save ``fig`` as ``path`` and send it to every logger that takes images."""
    fig.savefig(path, dpi=100)
    for lg in trainer.loggers:
        if isinstance(lg, TensorBoardLogger):
            lg.experiment.add_figure(tag, fig, global_step=trainer.global_step, close=False)
        elif isinstance(lg, MLFlowLogger):
            lg.experiment.log_figure(lg.run_id, fig, f"figures/{tag.replace('/', '_')}.png")
        elif isinstance(lg, WandbLogger):
            lg.log_image(key=tag, images=[str(path)])
    plt.close(fig)


class TimelineFigures(L.Callback):
    """After testing, draws the timelines and the trajectories of the first ``num_clips`` test clips into
    TensorBoard and ``output_dir`` (the test loader is not shuffled, so these are the test set's first
    clips), from the per-clip outputs that ``test_step`` returns for the first batch."""

    LABELS = {"truth": "truth", "per_step": "per step", "segments": "segments", "prior": "prior (online)"}

    def __init__(self, output_dir: str, num_clips: int = 4) -> None:
        self.output_dir, self.num_clips = Path(output_dir), num_clips
        self.clips: dict[str, torch.Tensor] = {}

    def on_test_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.clips = {}

    def on_test_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                          batch_idx: int, dataloader_idx: int = 0) -> None:
        if batch_idx != 0 or not isinstance(outputs, dict) or self.num_clips < 1:
            return
        k = self.num_clips
        self.clips = {key: outputs[key][:k].cpu() for key in ("segments", "prior", "per_step")}
        self.clips |= {"states": batch["states"][:k].cpu(), "mask": batch["mask"][:k].cpu(),
                       # test-set index of each clip: rank r of W holds clips r, r + W, ... under DDP
                       "index": torch.arange(len(self.clips["segments"])) * trainer.world_size + trainer.global_rank}
        if "edges" in batch:
            self.clips["truth"] = batch["edges"][:k].transpose(1, 2).cpu()

    def on_test_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self.clips or not trainer.is_global_zero:
            return
        try:
            self._draw(trainer, pl_module)
        except Exception as e:  # figures are an extra: a failure here must never cost the run its results
            log.warning("test figures not drawn (%s: %s); the metrics and exports are unaffected", type(e).__name__, e)

    def _draw(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        data = self.clips
        self.output_dir.mkdir(parents=True, exist_ok=True)
        num_types = pl_module.model.num_types
        dm = getattr(trainer, "datamodule", None)
        norm = getattr(dm, "normalizer", None)
        for i in range(data["segments"].shape[0]):
            index = int(data["index"][i])
            rows = {label: data[key][i] for key, label in self.LABELS.items() if key in data}
            fig = timeline_figure(rows, num_types, title=f"test clip {index}")
            _add(trainer, f"test/timeline/{i:02d}", fig, self.output_dir / f"timeline_{i:02d}.png")
            states = norm.denormalize(data["states"][i]) if norm is not None else data["states"][i]
            background = dm.background("test", index) if dm is not None and hasattr(dm, "background") else None
            fig = trajectory_figure(states[..., :2], data["mask"][i], data["segments"][i], num_types,
                                    background, title=f"test clip {index}: interaction segments")
            _add(trainer, f"test/trajectories/{i:02d}", fig, self.output_dir / f"trajectories_{i:02d}.png")
