"""Per-clip results gathered across batches (and DDP ranks) and written as the tables users read.

What a test or prediction step says about its clips
(:meth:`dider.models.vae.RelationalVAE.describe`) comes in batches whose agent counts differ (real
data are padded per batch). Here they are put back in dataset order, padded to one agent count, and
written as:

- a segment table (:func:`segment_frame`): one row per (clip, sender, receiver, segment) with its
  steps, type and probability, and the input's identifiers (clip index, scene, agent ids, frame
  numbers);
- ``clips.npz`` (:func:`write_clips_npz`): the arrays behind it, for the explorer and for analysis.

Shapes: S clips, T frames, N agents, E = N(N-1) edges (sender-major, :mod:`dider.graph`), K edge
types.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import pandas as pd
import torch

from dider.evaluation.type_meaning import profile_array
from dider.graph import edge_id, edge_index, num_agents
from dider.io import atomic_write, atomic_write_bytes

# Arrays over a clip's edges and transitions ([E, T-1, ...]): padded by re-indexing edges, not
# appending.
EDGE_KEYS = ("segments", "probs", "per_step", "prior", "truth", "step_probs")
# Arrays over a clip's agents ([T, N, ...] or [N]): padded by appending absent agents.
AGENT_KEYS = {"states": 1, "positions": 1, "mask": 1, "forecast": 1, "forecast_samples": 2,
              "agent": 0}  # key -> the agents' axis
# Fill values for what padding adds: absent edges and agents.
FILL = {"segments": -1, "per_step": -1, "prior": -1, "truth": -1, "agent": -1}


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
    prob_sum = (torch.zeros(len(starts), dtype=torch.float64)
                .index_add_(0, run_id, probs.flatten().double()))
    clip, rest = starts // (e * t), starts % (e * t)
    edge, start = rest // t, rest % t
    return torch.stack([clip.double(), edge.double(), start.double(),
                        (start + ends - starts).double(), types.flatten()[starts].double(),
                        prob_sum / (ends - starts).double()], dim=1)  # fmt: skip


def split_clips(batch: Mapping[str, Any]) -> list[dict[str, torch.Tensor]]:
    """A batch of per-clip outputs (each value [B, ...], or a dict of them such as ``source``) ->
    one dict per clip, on the CPU, with ``source`` flattened into the clip's keys (``clip``,
    ``scene``, ...)."""
    flat: dict[str, torch.Tensor] = {}
    for key, value in batch.items():
        if isinstance(value, Mapping):
            flat.update(value)
        elif isinstance(value, torch.Tensor):
            flat[key] = value
    size = next(iter(flat.values())).shape[0]
    cpu = {k: v.detach().cpu() for k, v in flat.items()}
    return [{k: v[i] for k, v in cpu.items()} for i in range(size)]


def gather_in_order(trainer: L.Trainer,
                    clips: list[dict[str, torch.Tensor]]) -> list[dict[str, torch.Tensor]]:
    """The clips of every rank in dataset order, on rank 0 (other ranks get []): under DDP rank r of
    W evaluates clips r, r + W, ... (the data modules' unrepeated sampler)."""
    world = trainer.world_size
    if world == 1:
        return clips
    per_rank: list[Any] | None = [None] * world if trainer.global_rank == 0 else None
    torch.distributed.gather_object(clips, per_rank, dst=0)
    if trainer.global_rank != 0:
        return []
    return [per_rank[r][j] for j in range(max(map(len, per_rank))) for r in range(world)
            if j < len(per_rank[r])]


def _pad_edges(value: torch.Tensor, n: int, n_max: int, fill: float) -> torch.Tensor:
    """[E_n, ...] over a clip of n agents -> [E_max, ...] in the edge order of n_max agents."""
    if n == n_max:
        return value
    send, recv = edge_index(n)
    out = torch.full((n_max * (n_max - 1), *value.shape[1:]), fill, dtype=value.dtype)
    out[edge_id(send, recv, n_max)] = value
    return out


def _pad_agents(value: torch.Tensor, axis: int, n_max: int, fill: float) -> torch.Tensor:
    missing = n_max - value.shape[axis]
    if missing == 0:
        return value
    shape = list(value.shape)
    shape[axis] = missing
    return torch.cat([value, torch.full(shape, fill, dtype=value.dtype)], dim=axis)


def stack_clips(clips: Sequence[Mapping[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Per-clip dicts (agent counts may differ) -> one dict of [S, ...] tensors padded to the
    largest count: absent edges are -1 (types) or 0, absent agents have mask False, zero states and
    id -1."""
    n_of = [num_agents(c["segments"].shape[0]) if "segments" in c else c["mask"].shape[-1]
            for c in clips]
    n_max = max(n_of)
    out: dict[str, torch.Tensor] = {}
    for key in clips[0]:
        fill = FILL.get(key, 0)
        if key in EDGE_KEYS:
            items = [_pad_edges(c[key], n, n_max, fill) for c, n in zip(clips, n_of, strict=True)]
        elif key in AGENT_KEYS:
            items = [_pad_agents(c[key], AGENT_KEYS[key], n_max, fill) for c in clips]
        else:
            items = [c[key] for c in clips]
        out[key] = torch.stack(items)
    return out


def segment_frame(arrays: Mapping[str, torch.Tensor], frame_step: int = 1,
                  names: Mapping[str, Sequence[str]] | None = None) -> pd.DataFrame:
    """The segment table of stacked clips (:func:`stack_clips`): one row per (clip, sender,
    receiver, segment) of a present edge.

    arrays: ``segments`` [S, E, T-1] long (-1 absent), ``probs`` [S, E, T-1], and the source
    identifiers that exist: ``clip`` [S] (else the clip's position), ``scene`` [S], ``frame`` [S]
    (the input's frame of step 0), ``agent`` [S, N]. frame_step: input frames per step. names:
    key -> names of string ids. Columns: clip, [scene], sender, receiver, [sender_id, receiver_id],
    segment, start_step, end_step, [start_frame, end_frame], type, prob. A segment covers the
    transitions start_step -> ... -> end_step, i.e. frames start_step..end_step of the clip (end
    exclusive as a transition index).
    """
    names = names or {}
    types = arrays["segments"].long()
    # [R, 6]: clip, edge, start, end, type, prob
    rows = segment_table(types, arrays["probs"].float())
    rows = rows[rows[:, 4] >= 0]
    pos, edge = rows[:, 0].long(), rows[:, 1].long()
    send, recv = edge_index(num_agents(types.shape[1]))
    table: dict[str, Any] = {"clip": (arrays["clip"][pos] if "clip" in arrays else pos).numpy()}
    if "scene" in arrays:
        table["scene"] = named(arrays["scene"][pos], names.get("scene"))
    table["sender"], table["receiver"] = send[edge].numpy(), recv[edge].numpy()
    if "agent" in arrays:
        ids = arrays["agent"]
        table["sender_id"] = named(ids[pos, send[edge]], names.get("agent"))
        table["receiver_id"] = named(ids[pos, recv[edge]], names.get("agent"))
    frame = pd.DataFrame(table)
    frame["segment"] = frame.groupby([pos.numpy(), edge.numpy()]).cumcount().to_numpy()
    start, end = rows[:, 2].long(), rows[:, 3].long()
    frame["start_step"], frame["end_step"] = start.numpy(), end.numpy()
    if "frame" in arrays:
        first = arrays["frame"][pos]
        frame["start_frame"] = (first + start * frame_step).numpy()
        frame["end_frame"] = (first + end * frame_step).numpy()
    frame["type"] = rows[:, 4].long().numpy()
    frame["prob"] = rows[:, 5].numpy().round(4)
    return frame


def named(ids: torch.Tensor, names: Sequence[str] | None) -> np.ndarray:
    """Integer ids, or their names when the input's ids were strings (codes into ``names``)."""
    values = ids.numpy()
    return values if names is None else np.asarray(names, dtype=object)[values]


def write_table(frame: pd.DataFrame, path: Path) -> list[Path]:
    """``path`` as CSV, and beside it as Parquet when pyarrow is installed; atomic. -> the files
    written."""
    atomic_write_bytes(path, frame.to_csv(index=False).encode())
    written = [path]
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        return written
    parquet = path.with_suffix(".parquet")
    buf = io.BytesIO()
    frame.to_parquet(buf, index=False)
    atomic_write_bytes(parquet, buf.getvalue())
    return [*written, parquet]


# The dtypes clips.npz stores each key in (compact; types fit int8 for up to 127 edge types).
NPZ_DTYPES = {"segments": np.int8, "per_step": np.int8, "prior": np.int8, "truth": np.int8,
              "probs": np.float16, "step_probs": np.float16, "positions": np.float64,
              "forecast": np.float64, "forecast_samples": np.float64, "mask": np.bool_}


def write_clips_npz(path: Path, arrays: Mapping[str, torch.Tensor],
                    extra: Mapping[str, np.ndarray]) -> None:
    """Stacked clips and ``extra`` arrays (``num_types``, ``model``, backgrounds...) -> ``path``,
    compressed, atomically; every key is a plain array (readable with ``allow_pickle=False``)."""
    # numpy has no bf16: a run trained in bf16 autocast may hand such tensors on
    plain = {k: v.float() if v.dtype == torch.bfloat16 else v for k, v in arrays.items()}
    out = ({k: v.numpy().astype(NPZ_DTYPES.get(k, v.numpy().dtype)) for k, v in plain.items()}
           | dict(extra))
    atomic_write(path, lambda f: np.savez_compressed(f, **out))


def explore_arrays(arrays: Mapping[str, torch.Tensor], dm: Any) -> dict[str, torch.Tensor]:
    """Stacked clips as ``clips.npz`` holds them: ``states`` become ``positions`` [S, T, N, 2]
    float64 in the user's coordinates (the data module's normaliser undone, its origin added; zeros
    where absent), the forecasts too; other keys are kept."""
    out = {k: v for k, v in arrays.items() if k != "states"}
    # a data set without source ids (synthetic): the clip's position in its split
    if "clip" not in out:
        out["clip"] = torch.arange(arrays["mask"].shape[0])
    norm = getattr(dm, "normalizer", None)
    user = ((lambda s: norm.to_user(norm.denormalize(s.double()))) if norm is not None
            else (lambda s: s.double()))
    if "states" in arrays:
        out["positions"] = user(arrays["states"])[..., :2] * arrays["mask"][..., None]
    for key in ("forecast", "forecast_samples"):
        if key in arrays:
            out[key] = user(arrays[key])[..., :2]
    return out


def explore_extras(pl_module: Any, dm: Any, split: str, arrays: Mapping[str, torch.Tensor],
                   scores: Mapping[str, float] | None = None) -> dict[str, np.ndarray]:
    """What the explorer needs besides the clips: ``num_types``, ``model``, what each type means
    (``type_profile``, from the ``split/typeK/...`` values in ``scores``,
    :mod:`dider.evaluation.type_meaning`) and the data set's scene images (``background_of`` [S]
    index of each clip's image or -1, ``background_K`` and ``background_K_extent``)."""
    model = pl_module.model if hasattr(pl_module, "model") else pl_module
    extra: dict[str, np.ndarray] = {"num_types": np.array(model.num_types),
                                    "model": np.array(str(model.name))}
    if (units := getattr(dm, "units", None)) is not None:
        extra["units"] = np.array(units)
    # input frames per step (data.downsample)
    extra["frame_step"] = np.array(int(getattr(dm, "frame_step", 1)))
    # string ids: ``agent`` holds their codes
    if names := getattr(dm, "source_names", {}).get("agent"):
        extra["agent_names"] = np.array([str(n) for n in names])
    if (profile := profile_array(scores or {}, split)) is not None:
        extra["type_profile"] = profile
    background = getattr(dm, "background", None)
    if background is None:
        return extra
    of, seen = np.full(arrays["mask"].shape[0], -1), {}
    for i in range(len(of)):  # a few images per data set (one per recording): cheap, not a hot path
        try:
            found = background(split, i)
        # an optional extra: never lose the results
        except (KeyError, IndexError, OSError, ValueError):
            found = None
        if found is None:
            continue
        image, extent = found
        key = (np.asarray(image).shape, tuple(extent))
        if key not in seen:
            k = seen[key] = len(seen)
            pixels = np.asarray(image)
            extra[f"background_{k}"] = ((pixels * 255).astype(np.uint8) if pixels.dtype.kind == "f"
                                        else pixels)
            extra[f"background_{k}_extent"] = np.asarray(extent, dtype=np.float64)
        of[i] = seen[key]
    extra["background_of"] = of
    return extra
