"""Figures: per-edge interaction timelines (ground truth against inferred), for TensorBoard and PNG."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from lightning.pytorch.loggers import TensorBoardLogger  # noqa: E402

from dider.graph import edge_index  # noqa: E402


def timeline_figure(rows: dict[str, torch.Tensor], num_types: int, title: str = "") -> plt.Figure:
    """One panel per edge, one band per source (ground truth, posterior, prior...), coloured by type.

    rows: name -> [E, T] long edge types of one clip.
    """
    names = list(rows)
    e, t = next(iter(rows.values())).shape
    n = int(round((1 + (1 + 4 * e) ** 0.5) / 2))
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


class TimelineFigures(L.Callback):
    """After testing, draws the timelines of the first test clips into TensorBoard and ``output_dir``."""

    def __init__(self, output_dir: str) -> None:
        self.output_dir = Path(output_dir)

    def on_test_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        data = getattr(pl_module, "figure_data", None)
        if not data or not trainer.is_global_zero:
            return
        self.output_dir.mkdir(parents=True, exist_ok=True)
        tb = next((lg for lg in trainer.loggers if isinstance(lg, TensorBoardLogger)), None)
        labels = {"truth": "truth", "per_step": "per step", "segments": "segments", "prior": "prior (online)"}
        for i in range(data["segments"].shape[0]):
            rows = {label: data[key][i] for key, label in labels.items() if key in data}
            fig = timeline_figure(rows, pl_module.num_types, title=f"test clip {i}")
            fig.savefig(self.output_dir / f"timeline_{i:02d}.png", dpi=100)
            if tb is not None:
                tb.experiment.add_figure(f"test/timeline/{i:02d}", fig, global_step=trainer.global_step, close=False)
            plt.close(fig)
