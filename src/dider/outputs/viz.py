"""Figures for TensorBoard and PNG: per-edge interaction timelines (ground truth against inferred)
and a clip's trajectories with its interaction segments drawn between the agents (over the scene
image if any)."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import lightning as L
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from lightning.pytorch.loggers import MLFlowLogger, TensorBoardLogger, WandbLogger  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from dider.evaluation.scoring import seeded_forecast  # noqa: E402
from dider.graph import edge_index, num_agents  # noqa: E402
from dider.io import atomic_write  # noqa: E402
from dider.models.baselines import ConstantVelocity  # noqa: E402

log = logging.getLogger(__name__)


def shown_edges(rows: dict[str, torch.Tensor], max_edges: int) -> torch.Tensor:
    """The edges a timeline draws: all when there are at most ``max_edges``, else the ``max_edges``
    with the most interaction steps (a type above 0 in any row), in edge order.

    rows: name -> [E, T] long edge types (-1 absent) -> [K] edge indices.
    """
    e = next(iter(rows.values())).shape[0]
    if e <= max_edges:
        return torch.arange(e)
    busy = sum((r > 0).sum(-1) for r in rows.values())  # [E]
    # a stable order: ties (e.g. no interaction at all) keep the lower edge index
    order = torch.argsort(busy * e + (e - 1 - torch.arange(e)), descending=True)
    return order[:max_edges].sort().values


def timeline_figure(rows: dict[str, torch.Tensor], num_types: int, title: str = "",
                    max_edges: int = 12) -> plt.Figure:
    """One band per shown edge (:func:`shown_edges`), one row per source (ground truth, posterior,
    prior...), coloured by type, absent steps white; drawn as one image, so its cost does not grow
    with the edges.

    rows: name -> [E, T] long edge types of one clip (-1 where the edge is absent).
    """
    names = list(rows)
    e, t = next(iter(rows.values())).shape
    n = num_agents(e)
    send, recv = edge_index(n)
    shown = shown_edges(rows, max_edges)
    r = len(names)
    # band k: rows k * (r + 1) ... + r - 1, then a blank separator row
    stacked = torch.stack([rows[name][shown] for name in names], 1).float()  # [K, R, T]
    img = (torch.cat([stacked, torch.full((len(shown), 1, t), float("nan"))], 1).reshape(-1, t)[:-1]
           .numpy())
    img[img < 0] = np.nan
    cmap = plt.get_cmap("tab10", max(num_types, 2)).with_extremes(bad="white")
    fig, ax = plt.subplots(figsize=(8, 0.16 * len(img) + 1.2))
    ax.imshow(img, aspect="auto", cmap=cmap, vmin=-0.5, vmax=max(num_types, 2) - 0.5,
              interpolation="nearest")
    ticks = [k * (r + 1) + j for k in range(len(shown)) for j in range(r)]
    labels = [f"{send[i].item()}→{recv[i].item()}  {name}" if j == 0 else name
              for i in shown.tolist() for j, name in enumerate(names)]
    ax.set_yticks(ticks, labels, fontsize=6)
    ax.set_xlabel("transition t → t+1")
    handles = [plt.Rectangle((0, 0), 1, 1, color=cmap(c)) for c in range(num_types)]
    legend = ["0: none"] + [f"{c}" for c in range(1, num_types)]
    fig.legend(handles, legend, loc="upper right", ncol=num_types, fontsize=7, title="edge type",
               title_fontsize=7)
    if len(shown) < e:
        title = f"{title}: {len(shown)} of {e} edges, those with the most interaction steps"
    fig.suptitle(title, fontsize=9, x=0.02, ha="left")
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    return fig


def trajectory_figure(positions: torch.Tensor, mask: torch.Tensor, types: torch.Tensor,
                      num_types: int,
                      background: tuple[object, tuple[float, float, float, float]] | None = None,
                      title: str = "") -> plt.Figure:
    """A clip's paths with a line from sender to receiver at every step an edge holds an interaction
    type, coloured by that type, so segments show where along the paths they happened.

    positions: [T, N, 2] raw units; mask: [T, N] bool; types: [E, T-1] long (transition t -> t+1
    drawn at frame t + 1); background: (image, extent) as from ``BaseDataModule.background``.
    """
    t, n = mask.shape
    send, recv = edge_index(n)
    cmap = plt.get_cmap("tab10", max(num_types, 2))
    fig, ax = plt.subplots(figsize=(6, 6))
    if background is not None:
        image, extent = background
        ax.imshow(image, extent=extent, zorder=0)
    pos, present = positions.numpy(), mask.numpy()
    # an edge exists for transition t -> t+1 when both agents are present at t (the model's edge
    # mask) and is drawn at frame t + 1, which needs them there too
    alive = present[:-1] & present[1:]
    both = (alive[:, send.numpy()] & alive[:, recv.numpy()]).T  # [E, T-1]
    e_idx, step = np.nonzero((types.numpy() > 0) & both)
    frame = step + 1
    # one collection per type: one artist however many edges and steps
    for c in range(1, num_types):
        keep = types.numpy()[e_idx, step] == c
        if keep.any():
            a, b = (pos[frame[keep], send[e_idx[keep]].numpy()],
                    pos[frame[keep], recv[e_idx[keep]].numpy()])
            ax.add_collection(LineCollection(np.stack([a, b], 1), colors=[cmap(c)], alpha=0.35,
                                             lw=1.0, zorder=1))
    ax.add_collection(LineCollection(path_steps(pos, present), colors="k", lw=1.2, zorder=2))
    seen = present.any(0)
    # [N] each agent's first and last frame
    first, last = present.argmax(0), t - 1 - present[::-1].argmax(0)
    agents = np.flatnonzero(seen)
    ax.scatter(pos[first[agents], agents, 0], pos[first[agents], agents, 1], s=12, color="k",
               zorder=3)
    if len(agents) <= 40:  # beyond that the numbers cover the paths
        for i in agents:
            ax.annotate(str(i), pos[last[i], i], fontsize=7, zorder=3)
    ax.autoscale_view()
    handles = [plt.Line2D([], [], color=cmap(c), lw=2) for c in range(1, num_types)]
    ax.legend(handles, [f"type {c}" for c in range(1, num_types)], fontsize=7, loc="best")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


def path_steps(pos: np.ndarray, present: np.ndarray) -> np.ndarray:
    """Every agent's path as line segments for one ``LineCollection``: a step is drawn where the
    agent is present at both ends. pos [T, N, 2], present [T, N] bool -> [P, 2, 2]."""
    return np.stack([pos[:-1], pos[1:]], 2)[present[:-1] & present[1:]]


def forecast_figure(positions: torch.Tensor, mask: torch.Tensor, forecast: torch.Tensor,
                    cv: torch.Tensor, burn_in: int, title: str = "",
                    samples: torch.Tensor | None = None) -> plt.Figure:
    """The true paths (observed part thin, future thick) against the model's forecast and constant
    velocity's from the burn-in's last frame, in data units, for the agents present there; one
    collection per kind of line; the sampled futures thin under them.

    positions: [T, N, 2]; mask: [T, N] bool; forecast, cv: [P, N, 2] for frames burn_in .. burn_in +
    P - 1; samples: [K, P, N, 2] or None."""
    pos, present = positions.numpy(), mask.numpy()
    carry = present[burn_in - 1]  # [N]
    fig, ax = plt.subplots(figsize=(6, 6))
    styles = {"true": {"colors": "k", "linestyles": "-"},
              "model": {"colors": "tab:red", "linestyles": "--"},
              "constant velocity": {"colors": "tab:gray", "linestyles": ":"}}
    ax.add_collection(LineCollection(path_steps(pos[:burn_in], present[:burn_in] & carry),
                                     colors="k", lw=0.8, alpha=0.5))
    ax.add_collection(LineCollection(path_steps(pos[burn_in - 1:], present[burn_in - 1:] & carry),
                                     lw=1.6, **styles["true"]))
    # [1, N, 2]: each forecast starts at the last observed position
    start = pos[burn_in - 1 : burn_in]
    ahead = np.broadcast_to(carry, (len(forecast) + 1, len(carry)))
    if samples is not None and len(samples):
        styles["sampled futures"] = {"colors": "tab:red", "linestyles": "-"}
        drawn = [step for future in samples.numpy()
                 for step in path_steps(np.concatenate([start, future]), ahead)]
        ax.add_collection(LineCollection(drawn, lw=0.6, alpha=0.35, **styles["sampled futures"]))
    for name, path in (("model", forecast), ("constant velocity", cv)):
        xy = np.concatenate([start, path.numpy()])
        ax.add_collection(LineCollection(path_steps(xy, ahead), lw=1.4, **styles[name]))
    ax.scatter(pos[burn_in - 1, carry, 0], pos[burn_in - 1, carry, 1], s=10, color="k", zorder=3)
    handles = [plt.Line2D([], [], color=st["colors"], ls=st["linestyles"], lw=1.5)
               for st in styles.values()]
    ax.legend(handles, list(styles), fontsize=7, loc="best")
    ax.autoscale_view()
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


def _add(trainer: L.Trainer, tag: str, fig: plt.Figure, path: Path) -> Path:
    """Save ``fig`` as ``path`` and send it to every logger that takes images -> ``path``."""
    atomic_write(path, lambda f: fig.savefig(f, dpi=100, format="png"))
    for lg in trainer.loggers:
        if isinstance(lg, TensorBoardLogger):
            lg.experiment.add_figure(tag, fig, global_step=trainer.global_step, close=False)
        elif isinstance(lg, MLFlowLogger):
            lg.experiment.log_figure(lg.run_id, fig, f"figures/{tag.replace('/', '_')}.png")
        elif isinstance(lg, WandbLogger):
            lg.log_image(key=tag, images=[str(path)])
    plt.close(fig)
    return path


class TimelineFigures(L.Callback):
    """The timelines and the trajectories of the first ``num_clips`` test clips, into TensorBoard
    and ``output_dir`` (the test loader is not shuffled, so these are the test set's first clips),
    from the per-clip outputs that ``test_step`` returns for the first batch.

    The test only keeps the clips; :meth:`draw` draws them, which the app calls once the results are
    on disk, so a figure never delays or costs them. Drawing stops after ``budget_s`` seconds."""

    LABELS = {"truth": "truth", "per_step": "per step", "segments": "segments",
              "prior": "prior (online)"}

    def __init__(self, output_dir: str, num_clips: int = 4, max_edges: int = 12,
                 budget_s: float = 120.0) -> None:
        self.output_dir, self.num_clips = Path(output_dir), num_clips
        self.max_edges, self.budget_s = max_edges, budget_s
        self.clips: dict[str, torch.Tensor] = {}

    def on_test_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.clips = {}

    def on_test_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any,
                          batch: Any, batch_idx: int, dataloader_idx: int = 0) -> None:
        if batch_idx != 0 or not isinstance(outputs, dict) or self.num_clips < 1:
            return
        k = self.num_clips
        absent = outputs["segments"][:k].cpu() < 0  # every row shows an absent edge-step as such
        self.clips = {key: outputs[key][:k].cpu().masked_fill(absent, -1)
                      for key in ("segments", "prior", "per_step")}
        self.clips |= {"states": batch["states"][:k].cpu(), "mask": batch["mask"][:k].cpu(),
                       # test-set index of each clip: rank r of W holds clips r, r + W, ... under
                       # DDP
                       "index": torch.arange(len(self.clips["segments"])) * trainer.world_size
                       + trainer.global_rank}
        if "edges" in batch:
            self.clips["truth"] = batch["edges"].transpose(1, 2)[:k].cpu().masked_fill(absent, -1)

    def draw(self, trainer: L.Trainer, pl_module: L.LightningModule) -> list[Path]:
        """Draws the kept clips (rank zero only) -> the PNGs written. A failure is logged, never
        raised: figures are an extra."""
        if not self.clips or not trainer.is_global_zero:
            return []
        written: list[Path] = []
        try:
            self._draw(trainer, pl_module, written)
        except Exception as e:
            log.warning("test figures not drawn (%s: %s); the metrics and exports are unaffected",
                        type(e).__name__, e)
        finally:
            self.clips = {}
        return written

    def _draw(self, trainer: L.Trainer, pl_module: L.LightningModule, written: list[Path]) -> None:
        data = self.clips
        self.output_dir.mkdir(parents=True, exist_ok=True)
        num_types = pl_module.model.num_types
        dm = getattr(trainer, "datamodule", None)
        norm = getattr(dm, "normalizer", None)
        started = time.perf_counter()
        for i in range(data["segments"].shape[0]):
            if (spent := time.perf_counter() - started) > self.budget_s:
                log.warning("test figures: stopped after %d of %d clips (%.0f s, budget %g s)", i,
                            data["segments"].shape[0], spent, self.budget_s)
                return
            index = int(data["index"][i])
            rows = {label: data[key][i] for key, label in self.LABELS.items() if key in data}
            fig = timeline_figure(rows, num_types, title=f"test clip {index}",
                                  max_edges=self.max_edges)
            written.append(_add(trainer, f"test/timeline/{i:02d}", fig,
                                self.output_dir / f"timeline_{i:02d}.png"))
            states = (norm.to_user(norm.denormalize(data["states"][i])) if norm is not None
                      else data["states"][i])
            background = (dm.background("test", index)
                          if dm is not None and hasattr(dm, "background") else None)
            fig = trajectory_figure(states[..., :2], data["mask"][i], data["segments"][i],
                                    num_types,
                                    background, title=f"test clip {index}: interaction segments")
            written.append(_add(trainer, f"test/trajectories/{i:02d}", fig,
                                self.output_dir / f"trajectories_{i:02d}.png"))
            if (forecast := self._forecast(pl_module, data["states"][i], data["mask"][i],
                                           norm)) is not None:
                pred, cv, futures = forecast
                burn_in = pl_module.protocol.burn_in
                fig = forecast_figure(states[..., :2], data["mask"][i], pred, cv, burn_in,
                                      title=f"test clip {index}: forecast from frame {burn_in}",
                                      samples=futures)
                written.append(_add(trainer, f"test/forecast/{i:02d}", fig,
                                    self.output_dir / f"forecast_{i:02d}.png"))

    @staticmethod
    @torch.no_grad()
    def _forecast(pl_module: L.LightningModule, states: torch.Tensor, mask: torch.Tensor,
                  norm: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None] | None:
        """The model's and constant velocity's forecast of one clip [T, N, 4] after the model's
        burn-in, in data units: ([P, N, 2], [P, N, 2]), drawn from ``eval_seed`` as evaluation
        draws, and the test pass's sampled futures (``protocol.samples`` K: [K, P, N, 2], else
        None); None if nothing follows it."""
        if not hasattr(pl_module, "protocol"):  # not dider's module: nothing to roll out
            return None
        model, burn_in, samples = (pl_module.model, int(pl_module.protocol.burn_in),
                                   int(pl_module.protocol.samples))
        steps = states.shape[0] - burn_in
        if steps < 1:
            return None
        pred = seeded_forecast(pl_module, states[None], mask[None], burn_in, steps)[0]
        x, m = states[None].to(pl_module.device), mask[None].to(pl_module.device)
        cv = model.forecast_after(x, m, burn_in, steps, ConstantVelocity())[0].float().cpu()
        futures = None
        if samples > 0 and model.decoder_edges:
            with torch.random.fork_rng(devices=[x.device] if x.device.type == "cuda" else []):
                torch.manual_seed(int(pl_module.eval_seed) + 1)
                futures = model.forecast_after(x, m, burn_in, steps, samples=samples)
            futures = futures[0].float().cpu()
        if norm is not None:
            user = lambda s: norm.to_user(norm.denormalize(s))  # noqa: E731
            pred, cv = user(pred), user(cv)
            futures = None if futures is None else user(futures)
        return pred[..., :2], cv[..., :2], None if futures is None else futures[..., :2]


def draw_figures(trainer: L.Trainer, pl_module: L.LightningModule) -> list[Path]:
    """Every figure callback's :meth:`TimelineFigures.draw`, after the results are written -> PNGs
    written."""
    return [p for cb in trainer.callbacks if isinstance(cb, TimelineFigures)
            for p in cb.draw(trainer, pl_module)]
