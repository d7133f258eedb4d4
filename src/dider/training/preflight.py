"""What is checked before any work: every setting's rule at once, the clip arithmetic, files named in the
config, and the settings that are valid but probably not meant (warnings)."""

from __future__ import annotations

import importlib.resources
import logging
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from dider import __version__
from dider.data.batch import Normalizer
from dider.perf import native_bf16, trains_on_cpu
from dider.protocol import MIN_STEPS, horizons_problem
from dider.settings import NODES, ForecastProtocol
from dider.shipped import resolve, unknown
from dider.training.overrides import RENAMED
from dider.validation import RULES, ConfigError, node_problems, problem, settings_problems

log = logging.getLogger(__name__)

MODES = ("train", "eval", "predict")

TABLE = "dider.data.track_sources.TableFile"  # data=table's source: its path is a .csv / .parquet file
# The key holding the clip length of each data module that knows it from its config alone.
CLIP_LENGTH_KEYS = ("data.source.num_steps", "data.windows.seq_len", "data.source.num_frames")


def validate_config(cfg: DictConfig) -> None:
    """Check the values that would otherwise fail late (after data preparation, or mid-training), before any
    work: raises :class:`ConfigError` listing every problem by its key."""
    problems: list[str] = []

    def get(key: str) -> Any:
        try:
            return OmegaConf.select(cfg, key, default=None, throw_on_resolution_failure=True)
        except Exception as e:  # an interpolation that cannot resolve, e.g. a missing environment variable
            problems.append(f"{key}: cannot resolve ({e})")
            return None

    for key in RULES:  # the rules every constructor applies too, here all at once before any work
        value = get(key)
        if value is not None and (found := problem(key, value)) is not None:
            problems.append(found)
    for section in ("model", "data"):  # the settings that their classes declare (SETTINGS)
        if (node := get(section)) is not None:
            try:
                plain = OmegaConf.to_container(node, resolve=True)
                problems += settings_problems(plain, section) + (stray_keys(plain) if section == "model" else [])
            except OmegaConfBaseException as e:  # an interpolation that cannot resolve: named here, not later
                problems.append(f"{section}: cannot resolve ({e})")
    for key, cls in NODES.items():  # the app's own nodes: unknown keys (+predict.foo=1) and their rules
        if (node := get(key)) is not None:
            problems += node_problems(cls, OmegaConf.to_container(node, resolve=True), key)
    if isinstance(node := get("model.protocol"), DictConfig):  # a model config that gives a protocol of its own
        problems += node_problems(ForecastProtocol, OmegaConf.to_container(node, resolve=True), "model.protocol")
    mode = get("mode")
    problems += _checkpoint_problems(mode, get("ckpt_path"))
    if mode != "predict":  # prediction uses the checkpoint's model and scores no data horizons
        problems += _protocol_problems(get)
    problems += _path_problems(get) + _logger_problems(get) + _trainer_choice_problems(get)
    if problems:
        moved = [f"{found}; 0.2 moved it to {RENAMED[key]}" if (key := found.split(":", 1)[0].split("=", 1)[0])
                 in RENAMED else found for found in _in_data_config(_once(problems, cfg))]
        raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(moved))
    for warning in config_warnings(cfg):
        log.warning(warning)


def _once(problems: list[str], cfg: DictConfig) -> list[str]:
    """One mistake, one line, under the key the user sets: copies of a ``protocol.*`` value that the data and the
    model interpolate are dropped, and the network's ``name`` and ``num_edges``, which interpolate the model's top,
    are named ``model.name`` / ``model.num_edges``. Problems read ``key=value: why``."""
    def head(found: str) -> tuple[str, str]:  # (key, value) of "key=value: why"
        key, _, value = found.split(": ", 1)[0].partition("=")
        return key, value

    protocol = {(key.rsplit(".", 1)[-1], value) for key, value in map(head, problems) if key.startswith("protocol.")}
    out: list[str] = []
    for found in problems:
        key, value = head(found)
        if not key.startswith("protocol.") and (key.rsplit(".", 1)[-1], value) in protocol:
            continue
        top = key.removeprefix("model.net.")
        if top in ("name", "num_edges") and key != top and (
                OmegaConf.select(cfg, key, default=0) == OmegaConf.select(cfg, f"model.{top}", default=1)):
            found = found.replace(key, f"model.{top}", 1)
        if found not in out:
            out.append(found)
    return out


def _in_data_config(problems: list[str]) -> list[str]:
    """A data source's class named with the data config that sets it (``data=NAME`` and its file, unless the
    command line set it): where the user changes it."""
    if not HydraConfig.initialized() or (choice := HydraConfig.get().runtime.choices.get("data")) is None:
        return problems
    where = f"data={choice}"
    for source in HydraConfig.get().runtime.config_sources:  # the first config folder that holds it is Hydra's
        folder = {"file": lambda p: Path(p), "pkg": lambda p: importlib.resources.files(p)}.get(source.schema)
        try:
            if folder is not None and (file := folder(source.path) / "data" / f"{choice}.yaml").is_file():
                where = f"data={choice}: {file}"
                break
        except (ImportError, TypeError, ValueError):  # a source that is not a folder here
            continue
    return [f"{found} ({where}, or the command line)" if found.startswith("data.source._target_") else found
            for found in problems]


def _checkpoint_problems(mode: Any, ckpt: Any) -> list[str]:
    """``mode`` and ``ckpt_path``: a known mode, a checkpoint where the mode needs one, and one that exists."""
    problems = []
    if mode not in MODES:
        problems.append(f"mode={mode!r}: expected one of {list(MODES)}")
    if mode in ("eval", "predict") and not ckpt:
        problems.append(f"ckpt_path: mode={mode} needs ckpt_path=PATH (a checkpoint file or a run folder, or last "
                        f"for eval)")
    if mode == "predict" and ckpt == "last":
        problems.append("ckpt_path=last: mode=predict writes a new run folder; give the trained run's folder or "
                        "one of its checkpoint files (RUN/checkpoints/last.ckpt or its best epoch_*.ckpt)")
    tested = mode in ("eval", "predict")  # a run folder is a checkpoint there, as for dider.load
    folder_ok = tested and ckpt and Path(str(ckpt)).expanduser().is_dir()
    # a shipped model's name (dider.pretrained()) there too; resuming a training needs a full checkpoint
    shipped = tested and ckpt and resolve(str(ckpt)) is not None
    if ckpt and ckpt != "last" and not folder_ok and not shipped and not Path(str(ckpt)).expanduser().is_file():
        problems.append(f"ckpt_path={ckpt}: no such checkpoint file"
                        + (f" or run folder, {unknown()}" if tested else ""))
    return problems


def _protocol_problems(get: Callable[[str], Any]) -> list[str]:
    """The forecast protocol's burn-in and horizons against the clip length, where the config states it, and the
    model's own where an override set them apart from the protocol (files are checked once they are read, and
    ``predict.burn_in`` against the clips it forecasts)."""
    problems = []
    clip_key = next((k for k in CLIP_LENGTH_KEYS if get(k) is not None), None)
    clip = get(clip_key) if clip_key else None
    protocol = {key: get(f"protocol.{key}") for key in ("burn_in", "horizons")}
    for section in ("protocol", "model.protocol"):
        values = {key: get(f"{section}.{key}") for key in ("burn_in", "horizons")}
        if section != "protocol" and values == protocol:
            continue  # the protocol's, checked above
        burn_in = values["burn_in"]  # its own rule (an integer >= 1) is among the protocol's SETTINGS
        burn_in = burn_in if isinstance(burn_in, int) and burn_in >= 1 else None
        if burn_in is not None and isinstance(clip, int) and burn_in >= clip:
            problems.append(f"{section}.burn_in={burn_in}: must be shorter than the clips ({clip_key}={clip})")
        if values["horizons"] is None:
            continue
        longest = clip - burn_in if isinstance(clip, int) and isinstance(burn_in, int) else None
        longest = longest if longest is not None and longest >= 1 else None  # else burn_in is reported above
        context = f"the predicted steps after {section}.burn_in={burn_in} of {clip_key}={clip}"
        found = horizons_problem(values["horizons"], longest, f"{section}.horizons", context, integers=True)
        if found is not None:
            problems.append(found)
    return problems


def _path_problems(get: Callable[[str], Any]) -> list[str]:
    """The data's input folder or file, where the config names one: it must exist."""
    problems = []
    # a table's path is its file; a format's (any other source with a path) may be a folder of files
    path_kind = "file" if get("data.source._target_") in (None, TABLE) else "file or folder"
    for key, kind in (("data.source.root", "folder"), ("data.source.path", path_kind)):
        value = get(key)
        if value is None:
            continue
        path = Path(str(value)).expanduser()
        found = {"folder": path.is_dir(), "file": path.is_file(), "file or folder": path.exists()}[kind]
        if not found:
            problems.append(f"{key}={value}: no such {kind}")
    return problems


def _trainer_choice_problems(get: Callable[[str], Any]) -> list[str]:
    """``trainer=gpu`` picked but the accelerator left on the CPU: the CPU-sized experiments (applied after the
    trainer group) pin ``trainer.accelerator: cpu``, which would train on the CPU without a word."""
    if not HydraConfig.initialized() or HydraConfig.get().runtime.choices.get("trainer") != "gpu":
        return []
    if (accelerator := get("trainer.accelerator")) == "cpu":
        return [f"trainer=gpu with trainer.accelerator={accelerator} (set after the trainer group, by an "
                "experiment sized for a CPU): add trainer.accelerator=gpu to train on the GPU"]
    return []


def _logger_problems(get: Callable[[str], Any]) -> list[str]:
    """The loggers' local tracking stores: one that cannot be written fails late, after retries."""
    problems = []
    for name, node in (get("logger") or {}).items():
        for field in ("tracking_uri", "artifact_location"):
            value = get(f"logger.{name}.{field}") if isinstance(node, DictConfig) else None
            if isinstance(value, str) and (found := _store_problem(value)):
                problems.append(f"logger.{name}.{field}={value}: {found}")
    return problems


def _store_problem(uri: str) -> str | None:
    """A local tracking store (``sqlite:///PATH``, ``file:PATH`` or a plain path) whose folder cannot be
    created or written: what is wrong, else None (remote stores are not checked)."""
    if uri.startswith("sqlite:///"):
        folder = Path(uri.removeprefix("sqlite:///")).parent
    elif uri.startswith("file:"):
        folder = Path(uri.removeprefix("file:").removeprefix("//"))
    elif "://" in uri:
        return None
    else:
        folder = Path(uri)
    folder = folder.expanduser()
    existing = next((p for p in (folder, *folder.parents) if p.exists()), None)
    if existing is None or not existing.is_dir():
        return f"{existing} is not a folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"{existing} is not writable (choose a store in a folder you can write)"
    return None


# The top-level keys the app reads (experiments may add lookup tables such as edges_per_model).
TOP_LEVEL_KEYS = {"seed", "mode", "ckpt_path", "deterministic", "threads", "allocator", "compile", "cuda_graph",
                  "output_dir", "optimized_metric", "eval", "predict", "protocol", "data", "model", "trainer", "logger",
                  "callbacks", "hydra", "hparams_search", "edges_per_model", "trust"}


def config_warnings(cfg: DictConfig) -> list[str]:
    """Settings that are valid but probably not meant, each named: a run that trains nothing, bf16 emulated on a
    CPU, top-level keys nothing reads (a `+key=value` typo)."""
    found = []
    if cfg.get("mode") == "train" and OmegaConf.select(cfg, "trainer.max_epochs") == 0:
        found.append("trainer.max_epochs=0: nothing is trained; the test scores the initial weights")
    precision, accelerator = OmegaConf.select(cfg, "trainer.precision"), OmegaConf.select(cfg, "trainer.accelerator")
    if "bf16" in str(precision) and trains_on_cpu(accelerator) and not native_bf16("cpu"):
        found.append(f"trainer.precision={precision}: this CPU has no native bf16 (no AVX-512), so autocast "
                     "emulates it, many times slower than fp32 (trainer.precision=32-true)")
    if unknown := sorted(set(cfg.keys()) - TOP_LEVEL_KEYS):
        found.append(f"{', '.join(unknown)}: top-level key(s) that nothing reads (a typo of {sorted(TOP_LEVEL_KEYS)}?)")
    return found


def version_problem(theirs: str, ours: str = __version__) -> str | None:
    """A checkpoint written by another major or minor version than this package's: what to say, else None
    (patch releases keep checkpoints compatible)."""
    if not theirs:
        return "the checkpoint records no package version"
    if theirs.split(".")[:2] == ours.split(".")[:2]:
        return None
    return (f"the checkpoint was written by dider {theirs}, this is {ours}: another minor or major version may "
            f"read its settings differently; check its results, or retrain with {ours}")


def clip_problem(steps: int, where: str, burn_in: int | None = None, forecast_steps: int | None = None) -> str | None:
    """The clips of a prediction set, ``steps`` steps of the model's input each, against what the model needs
    (``MIN_STEPS``) and the forecast's burn-in: what is wrong, else None."""
    if steps < MIN_STEPS:
        return (f"{where}: its clips give {steps} step(s) of the model's input; the model needs >= {MIN_STEPS} (one "
                f"transition; finite-difference velocities use one more frame)")
    if forecast_steps and burn_in is not None and burn_in > steps:
        return (f"predict.burn_in={burn_in}: longer than the {steps} steps of the clips of {where}; the forecast "
                f"starts after the burn-in, so it must be <= {steps}")
    return None


def input_warnings(states: torch.Tensor, mask: torch.Tensor, normalizer: Normalizer, where: str,
                   factor: float = 10.0) -> list[str]:
    """New input against a trained model's normaliser: no agent present at all, or positions / velocities
    spreading over ``factor`` times the training data's range (a unit mismatch reads as finite nonsense).

    states: [..., 4] normalised (the normaliser's [-1, 1] on the training data); mask: states.shape[:-1] bool.
    """
    if not bool(mask.any()):
        return [f"{where}: no agent is present at any frame; the outputs will be empty"]
    found = []
    present = states[mask]  # [P, 4]
    for cols, what, (lo, hi) in (((0, 1), "positions", normalizer.pos_range), ((2, 3), "velocities",
                                                                               normalizer.vel_range)):
        scale = present[:, list(cols)].abs().max().item()
        if scale > factor:
            raw = normalizer.denormalize(present)[:, list(cols)]
            found.append(f"{where}: {what} span [{raw.min().item():.4g}, {raw.max().item():.4g}], about "
                         f"{scale:.0f}x the training data's [{lo:.4g}, {hi:.4g}]: other units (cm for m?), another "
                         f"frame rate or coordinate frame? The model's outputs there are extrapolations")
    return found


def stray_keys(node: Mapping[str, Any]) -> list[str]:
    """What is wrong with the top-level keys of a model config (``cfg.model``): a key that is neither the
    LightningModule's (its constructor's arguments) nor ``name`` / ``num_edges`` (a network setting written at the
    top, say, which would otherwise be ignored)."""
    from dider.training.building import SETTINGS  # it imports the models: only here

    known = {*SETTINGS, "name", "num_edges"}
    return [f"model.{k}: not a setting of the model's top level ({sorted(known)}); the network's settings are "
            f"under model.net (model.net.{k})" for k in node if k not in known and k != "_target_"]


def check_monitors(model: Any, cfg: DictConfig) -> None:
    """A checkpoint or early-stopping callback that monitors a metric the model never logs would fail only after the
    first epoch: named before training, with the key that sets it."""
    known = model.monitorable()
    if (metric := cfg.get("optimized_metric")) and metric not in known:  # a search would score every trial inf
        close = sorted(k for k in known if k.startswith("val/"))
        raise ConfigError(f"optimized_metric={metric}: the model logs no such metric; e.g. {', '.join(close[:8])}")
    for name, node in (cfg.get("callbacks") or {}).items():
        monitor = node.get("monitor") if isinstance(node, DictConfig) else None
        if monitor and monitor not in known:
            close = sorted(k for k in known if k.split("/")[0] == str(monitor).split("/")[0])
            raise ConfigError(f"callbacks.{name}.monitor={monitor}: the model logs no such metric; e.g. "
                              f"{', '.join(close[:8]) or ', '.join(sorted(known)[:8])}")
