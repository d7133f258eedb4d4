"""A trained model as a Python object: ``dider.load(run_or_checkpoint)`` -> :class:`TrainedModel`.

The checkpoint describes itself (the model config, the data's normaliser and feature layout, the
package version), so new trajectories are read the way the training data were, with no data module
and no training data::

    model = dider.load("runs/RUN")        # a run folder or a .ckpt file
    segs = model.segments(positions, frame_rate=2.5)        # pandas DataFrame, one row per segment
    future = model.forecast(positions, burn_in=5, steps=20)  # [S, 20, N, 2] positions

Nothing here needs Lightning. Shapes: S clips, T frames, N agents, E = N(N-1) edges, K edge types.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from dider.data.batch import Normalizer
from dider.data.readers.trajectories import trajectory_states
from dider.io import read_run_record
from dider.models.checkpoint_format import read
from dider.models.vae import RelationalVAE
from dider.outputs.clips import segment_frame
from dider.protocol import MIN_STEPS, fill_absent
from dider.shipped import resolve, unknown
from dider.targets import Untrusted, check
from dider.training.preflight import input_warnings, version_problem
from dider.validation import above, check_arguments, integer, optional

ArrayLike = np.ndarray | torch.Tensor
log = logging.getLogger(__name__)


def find_checkpoint(path: str | Path) -> Path:
    """A checkpoint file, or a run folder's: the best checkpoint its ``metrics.json`` names, else
    ``checkpoints/last.ckpt``; or a shipped model's name (``dider.pretrained()``) that no file or
    folder has."""
    path = Path(path).expanduser()
    if path.is_file():
        return path
    if not path.is_dir():
        if (shipped := resolve(path)) is not None:
            return shipped
        raise FileNotFoundError(f"{path}: no such checkpoint file or run folder, {unknown()}")
    record = path / "metrics.json"
    if record.is_file() and (best := read_run_record(record).get("checkpoint")):
        # relative to the folder (a copied or moved folder finds its own best file); an absolute one
        # (an evaluation's of another folder's checkpoint) is looked for by its name among the
        # folder's checkpoints first
        found = ([path / best] if not Path(best).is_absolute()
                 else [path / "checkpoints" / Path(best).name, Path(best)])
        if files := [f for f in found if f.is_file()]:
            return files[0]
    last = path / "checkpoints" / "last.ckpt"
    if last.is_file():
        return last
    raise FileNotFoundError(f"{path}: a run folder with no checkpoint (looked for the best one in "
                            f"metrics.json and for {last})")


def read_checkpoint(path: Path) -> dict[str, Any]:
    """The checkpoint's contents (tensors and plain values only: ``weights_only``), with a named
    error for a file that is not one, or one written before checkpoints described themselves."""
    ckpt = read(path)  # a training checkpoint of today's format (anything else refused by name)
    bad = [k for k, v in ckpt["state_dict"].items()
           if isinstance(v, torch.Tensor) and v.is_floating_point()
           and not bool(torch.isfinite(v).all())]
    if bad:
        raise ValueError(f"{path}: {len(bad)} weight tensor(s) hold NaN or inf (e.g. "
                         f"{', '.join(bad[:3])}): the run that wrote it diverged; use a checkpoint "
                         "from before (checkpoints/), or train again with a lower "
                         "model.optimizer.lr")
    data = (ckpt.get("dider") or {}).get("data") or {}
    missing = [what for what, ok in (("the package version",
                                      "version" in (ckpt.get("dider") or {})),
                                     ("the data normaliser", "normalizer" in data.get("state", {})))
               if not ok]
    if missing:
        raise ValueError(f"{path}: this checkpoint lacks {' and '.join(missing)} (written by an "
                         "older version, or by a model trained without a data module), so new data "
                         "cannot be normalised the way its training data were; retrain with this "
                         "version, or evaluate it on its own data set with `python -m dider.run "
                         f"mode=eval ckpt_path={path} data=...`")
    return ckpt


@dataclass
class TrainedModel:
    """A trained network with what it needs to read new data: the normaliser and the training data's
    settings (``data``: the data module's arguments as its config nests them; :meth:`data_setting`
    finds one). ``config`` is the model config as the app's ``cfg.model`` holds it: the
    LightningModule's settings (the forecast ``protocol`` among them), ``name``, ``num_edges`` and
    the network's ``net``."""

    network: RelationalVAE
    normalizer: Normalizer
    config: dict[str, Any]
    data: dict[str, Any] = field(default_factory=dict)
    version: str = ""
    path: Path | None = None
    # the classes of the user's own that its config was allowed to build
    trust: tuple[str, ...] = ()
    # clips the network reads at once (as mode=predict's data.loader.eval_batch_size): the memory of
    # a call is that of one batch, whatever the number of clips; a progress line every progress_s
    # seconds of a long call
    batch_size: int = 256
    progress_s: float = 30.0

    def _batched(self, count: int, run: Callable[[slice], Any]) -> list[Any]:
        """``run`` on each batch of ``count`` clips (a slice of them) in order -> its results, with
        progress lines."""
        check_arguments("TrainedModel", {"batch_size": (self.batch_size, integer(1))})
        parts, started = [], time.monotonic()
        shown = started
        for lo in range(0, count, self.batch_size):
            parts.append(run(slice(lo, lo + self.batch_size)))
            if ((now := time.monotonic()) - shown >= self.progress_s
                and lo + self.batch_size < count):
                done = lo + self.batch_size
                log.info("%d of %d clips (%.0f s, about %.0f s left)", done, count, now - started,
                         (now - started) * (count - done) / done)
                shown = now
        return parts

    def data_setting(self, key: str) -> Any:
        """The training data's setting ``key`` (``frame_rate``, ``downsample``) where its data
        module keeps it: its source's, its cut's (``windows``) or its own; None where the data had
        none."""
        path = setting_path(self.data, key)
        return None if path is None else _get(self.data, path)

    @property
    def device(self) -> torch.device:
        return next(self.network.parameters()).device

    def to(self, device: str | torch.device) -> TrainedModel:
        self.network.to(device)
        return self

    def states(self, positions: ArrayLike, mask: ArrayLike | None = None,
               velocities: ArrayLike | None = None,
               frame_rate: float | None = None) -> tuple[torch.Tensor, torch.Tensor, int]:
        """Raw trajectories -> normalised model input: states [S, T', N, 4], mask [S, T', N] and the
        input's index of step 0 (1 when velocities come from finite differences, which use the first
        frame).

        positions [S, T, N, 2] or [T, N, 2]; mask the same without the last axis (absent agents may
        be NaN); velocities like positions, else (pos[t] - pos[t-1]) * frame_rate, the rate of the
        given frames (default: the training data's steps per second, its ``frame_rate`` /
        ``downsample``: give positions at the model's step rate)."""
        check_arguments("TrainedModel", {"frame_rate": (frame_rate, optional(above(0)))})
        arrays = {"positions": _numpy(positions, "positions")}
        single = arrays["positions"].ndim == 3
        for key, value in (("mask", mask), ("velocities", velocities)):
            if value is not None:
                arrays[key] = _numpy(value, key)
        if single:
            arrays = {k: v[None] for k, v in arrays.items()}
        if velocities is None and frame_rate is None:
            frame_rate = self.data_setting("frame_rate")
            if frame_rate is not None:  # the training data's steps: every downsample-th frame
                frame_rate = frame_rate / (self.data_setting("downsample") or 1)
            if frame_rate is None:
                raise ValueError("frame_rate: needed for finite-difference velocities (the "
                                 "training data did not record one); pass frame_rate=... or "
                                 "velocities=...")
        data = trajectory_states(arrays, "input", float(frame_rate or 1.0), self.normalizer.origin)
        if (steps := data["states"].shape[1]) < MIN_STEPS:
            how = "" if velocities is not None else " with finite-difference velocities"
            raise ValueError(f"positions: {arrays['positions'].shape[1]} frame(s) a clip give "
                             f"{steps} step(s) of the model's input; it needs >= {MIN_STEPS} (one "
                             f"transition), i.e. >= {MIN_STEPS + data['first_frame']} frames{how}")
        states = fill_absent(self.normalizer.normalize(data["states"]), data["mask"])
        for warning in input_warnings(states, data["mask"], self.normalizer, "positions"):
            log.warning(warning)
        return states.to(self.device), data["mask"].to(self.device), int(data["first_frame"])

    @torch.no_grad()
    def describe(self, states: torch.Tensor, mask: torch.Tensor) -> dict[str, torch.Tensor]:
        """:meth:`RelationalVAE.describe` of normalised states [S, T, N, 4] and mask [S, T, N] (eval
        mode), a batch of ``batch_size`` clips at a time (on the host)."""
        self.network.eval()

        def run(part: slice) -> dict[str, torch.Tensor]:
            x, m = states[part], mask[part]
            return {k: v.cpu()
                    for k, v in self.network.describe(self.network.infer({"states": x, "mask": m},
                                                                          hard=True), m).items()}

        parts = self._batched(states.shape[0], run)
        return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}

    def segments(self, positions: ArrayLike, mask: ArrayLike | None = None,
                 velocities: ArrayLike | None = None,
                 frame_rate: float | None = None) -> pd.DataFrame:
        """The interaction segments of every edge: one row per (clip, sender, receiver, segment)
        with ``start_step``/``end_step`` (the segment covers frames start..end of the model's
        input), the same in the input's frame numbers (``start_frame``/``end_frame``), ``type`` and
        ``prob``. Inputs as in :meth:`states`."""
        states, m, first = self.states(positions, mask, velocities, frame_rate)
        out = self.describe(states, m)
        s = states.shape[0]
        arrays = {"segments": out["segments"], "probs": out["probs"], "clip": torch.arange(s),
                  "frame": torch.full((s,), first)}
        return segment_frame(arrays)

    def edge_probabilities(self, positions: ArrayLike, mask: ArrayLike | None = None,
                           velocities: ArrayLike | None = None,
                           frame_rate: float | None = None) -> np.ndarray:
        """Per-step posterior probabilities of each edge type, [S, E, T'-1, K] (transition t ->
        t+1)."""
        states, m, _ = self.states(positions, mask, velocities, frame_rate)
        return self.describe(states, m)["step_probs"].numpy()

    @torch.no_grad()
    def forecast(self, positions: ArrayLike, burn_in: int, steps: int,
                 mask: ArrayLike | None = None,
                 velocities: ArrayLike | None = None, frame_rate: float | None = None,
                 seed: int | None = None, samples: int = 0) -> np.ndarray:
        """Positions [S, steps, N, 2] (input units) after the first ``burn_in`` frames of the
        model's input (frames 1..burn_in of the input with finite-difference velocities); agents
        present at the burn-in's last frame carry on, others are NaN. A model that samples its
        roll-out edges (DNRI's default) draws them from ``seed`` (default: the model's
        ``eval_seed``, as evaluation and ``mode=predict`` do), leaving the global random state
        alone. ``samples`` K > 0: K sampled futures instead, their online edges drawn from the prior
        (types and segment ends) -> [K, S, steps, N, 2]."""
        check_arguments("TrainedModel.forecast",
                        {"burn_in": (burn_in, integer(1)), "steps": (steps, integer(1)),
                         "seed": (seed, optional(integer(0, "", 2**64 - 1))),
                         "samples": (samples, integer(0))})
        states, m, _ = self.states(positions, mask, velocities, frame_rate)
        if burn_in > states.shape[1]:
            raise ValueError(f"TrainedModel.forecast: burn_in={burn_in}: more than the "
                             f"{states.shape[1]} steps of the model's input the clips give")
        self.network.eval()
        # seeded once, drawn batch after batch as mode=predict draws
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.config.get("eval_seed", 0) if seed is None else seed)
            pred = torch.cat(self._batched(
                states.shape[0], lambda part: self.network.forecast_after(
                    states[part], m[part], burn_in, steps, samples=samples).float().cpu()))
        if samples:  # [S, K, ...] -> [K, S, ...]
            pred = pred.transpose(0, 1)
        xy = self.normalizer.to_user(self.normalizer.denormalize(pred))[..., :2]
        return xy.masked_fill(~m[:, burn_in - 1, None, :, None].cpu(), float("nan")).numpy()


# The data settings that shape the features a model reads (velocities are finite differences x
# frame_rate / downsample; steps faster than max_speed are absent): new data must be read with the
# training data's values.
FEATURE_SETTINGS = ("frame_rate", "downsample", "max_speed")


def training_settings(trained: TrainedModel, given: Mapping[str, Any], set_by_user: Collection[str],
                      force: bool = False, where: str = "data",
                      force_key: str = "predict.force") -> dict[str, Any]:
    """The values of :data:`FEATURE_SETTINGS` that reading new data for ``trained`` needs, for the
    keys that both ``given`` (the data config; a key read in its ``source`` or ``windows`` node
    where it has one there) and the checkpoint have: the checkpoint's where the user did not set the
    key (``set_by_user`` holds ``where.path`` names), the user's where set and equal or ``force``. A
    value set and different raises a ValueError naming both (and ``force_key``, the setting that
    forces it). Returns the paths (``windows.downsample``) whose value changes, with it."""
    take: dict[str, Any] = {}
    for key in FEATURE_SETTINGS:
        path, recorded = setting_path(given, key), setting_path(trained.data, key)
        if (path is None or recorded is None
            or _get(given, path) == (theirs := _get(trained.data, recorded))):
            continue
        name = f"{where}.{path}"
        if name not in set_by_user:
            take[path] = theirs
        elif not force:
            raise ValueError(f"{name}={_get(given, path)}: the checkpoint {trained.path} was "
                             f"trained with {name}={theirs}, which shapes the features it reads "
                             f"(velocities); leave {name} out to use {theirs}, or set "
                             f"{force_key}=true to read the data with {_get(given, path)} anyway")
    return take


def setting_path(node: Mapping[str, Any], key: str) -> str | None:
    """Where a data config (or a checkpoint's data arguments) keeps the setting ``key``:
    ``source.<key>``, ``windows.<key>`` or ``<key>``, the first it has; None where it has none."""
    return next((p for p in (f"source.{key}", f"windows.{key}", key) if _has(node, p)), None)


def _has(node: Mapping[str, Any], path: str) -> bool:
    *parents, leaf = path.split(".")
    for parent in parents:
        node = node.get(parent) if isinstance(node, Mapping) else None
    return isinstance(node, Mapping) and leaf in node


def _get(node: Mapping[str, Any], path: str) -> Any:
    for part in path.split("."):
        node = node[part]
    return node


def _numpy(value: ArrayLike, name: str) -> np.ndarray:
    """An argument as an array; a ragged one (clips or agents of different lengths) named."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy()
    try:
        out = np.asarray(value, dtype=np.bool_ if name == "mask" else np.float64)
    except (ValueError, TypeError) as e:
        raise ValueError(f"{name}: not a rectangular array of numbers ({str(e).splitlines()[0]}); "
                         "pad clips and agents to one shape ([S, T, N, 2] for positions, NaN where "
                         "absent) and pass mask=[S, T, N]") from None
    return out


def load(path: str | Path, device: str | torch.device = "cpu",
         trust: Collection[str] = ()) -> TrainedModel:
    """A trained model from a run folder or a checkpoint file, ready on ``device`` in eval mode.

    The checkpoint's model config is data: it builds dider's own classes only, each where its kind
    goes, and any other ``_target_`` is refused naming the file, the key and the target, before
    anything is imported or called (:mod:`dider.targets`). ``trust``: dotted paths of classes of
    your own the checkpoint may build (a plugin in your package,
    ``["mypkg.encoders.MyEncoder"]``)."""
    ckpt_path = find_checkpoint(path)
    ckpt = read_checkpoint(ckpt_path)
    hparams: Mapping[str, Any] = ckpt["hyper_parameters"]
    # before anything is built: Untrusted names it
    check(hparams, "module", ckpt_path, "hyper_parameters", trust)
    try:  # a damaged or hand-edited checkpoint: named with the file and the part that does not fit
        net = hparams["net"]
        config = ({k: v for k, v in hparams.items() if k != "net"}
                  | {"name": net.get("name"), "num_edges": net.get("num_edges"), "net": net})
        network = RelationalVAE.from_file_config(net, ckpt_path, trust=trust)
    except Untrusted:
        raise
    except Exception as e:  # noqa: BLE001 (a plugin's checks or a missing key: any of them)
        raise ValueError(f"{ckpt_path}: its model config (hyper_parameters) does not build a model "
                         f"({type(e).__name__}: {e})") from e
    state = {k.removeprefix("model."): v for k, v in ckpt["state_dict"].items()}
    try:
        network.load_state_dict(state)
    except RuntimeError as e:  # missing, unexpected or mis-shaped weights
        raise ValueError(f"{ckpt_path}: its weights (state_dict) do not fit the model its config "
                         f"describes: {' '.join(str(e).split())[:400]}") from e
    data = ckpt["dider"]["data"]
    if warning := version_problem(ckpt["dider"].get("version", "")):
        log.warning("%s: %s", ckpt_path, warning)
    try:
        normalizer = Normalizer(**data["state"]["normalizer"])
    except (TypeError, ValueError, KeyError) as e:
        raise ValueError(f"{ckpt_path}: its data normaliser ({data['state']['normalizer']!r}) is "
                         f"damaged: {e}") from e
    return TrainedModel(network.to(device).eval(), normalizer, config, dict(data.get("args", {})),
                        ckpt["dider"].get("version", ""), ckpt_path, tuple(trust))
