"""What a run records about itself: the settings its loggers compare, where its results came from
(versions, commit, device, wall time), the results its TensorBoard HParams tab and text tab show,
and ``metrics.json``."""

from __future__ import annotations

import json
import math
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from lightning.pytorch.loggers import Logger, TensorBoardLogger
from omegaconf import DictConfig, OmegaConf

from dider import __version__
from dider.evaluation.scoring import leading_first
from dider.io import atomic_write_text
from dider.outputs.results_card import results_markdown


def hparam_metrics(cfg: DictConfig) -> list[str]:
    """The metrics shown in TensorBoard's HParams tab: at the data set's own horizons the forecast's
    ADE over constant velocity's and its ADE in data units; the edge recall (where the data have
    ground truth); the model-selection objective. Not the normalised MSE: the tab shows three
    decimals, and MSEs of 1e-4 read 0.000 there (they are in the scalars and the results card)."""
    # the scored ones
    horizons = OmegaConf.select(cfg, "model.protocol.horizons", default=None) or []
    return [*(f"test/ade_vs_cv/h{int(h):02d}" for h in horizons),
            *(f"test/ade/h{int(h):02d}" for h in horizons),
            "test/edge_acc/posterior/interaction", "test/edge_acc/prior/interaction", "val/select"]


def provenance(started: float, device: str) -> dict[str, Any]:
    """Where a result came from: package, torch and lightning versions, the git commit (when the
    package runs from a repository), the device and the wall time."""
    record: dict[str, Any] = {"dider": __version__, "torch": torch.__version__,
                              "lightning": L.__version__, "python": platform.python_version(),
                              "device": device, "wall_s": round(time.time() - started, 1)}
    if (commit := git_commit()) is not None:
        record["git_commit"] = commit
    return record


def git_commit() -> str | None:
    """The commit of the repository the package runs from (``-dirty`` when tracked files differ from
    it); None for an installed package."""
    root = Path(__file__).resolve().parents[3]  # src/dider/outputs/ -> the repository
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True,
                                text=True, timeout=10)
        if commit.returncode != 0:
            return None
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain",
                                "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):  # no git
        return None
    return commit.stdout.strip() + ("-dirty" if dirty else "")


def command_line(prog: str, argv: Sequence[str] | None) -> str:
    """The command that produced a tool's output (``prog`` and its arguments, shell-quoted), kept in
    the JSON it writes so that a committed record says how to make it again."""
    return " ".join([prog, shlex.join(sys.argv[1:] if argv is None else argv)]).rstrip()


def overrides() -> list[str]:
    try:
        return list(HydraConfig.get().overrides.task)
    except ValueError:  # composed outside a Hydra app
        return []


def in_sweep() -> bool:
    """Whether this process runs a job of a Hydra multirun (its folder is the job's own)."""
    try:
        return str(HydraConfig.get().mode) == "RunMode.MULTIRUN"
    except ValueError:
        return False


def run_dir_given() -> bool:
    """Whether the run folder was chosen (hydra.run.dir on the command line, or a sweep's job
    folder), rather than a new timestamped one."""
    try:
        hydra_cfg = HydraConfig.get()
    except ValueError:  # composed outside a Hydra app: the caller set the folder
        return True
    return str(hydra_cfg.mode) == "RunMode.MULTIRUN" or any(
        o.startswith(("hydra.run.dir=", "hydra.sweep.dir=")) for o in hydra_cfg.overrides.hydra)


def resume_command(cfg: DictConfig, out_dir: Path, ckpt: str | None) -> str:
    """The command that repeats an interrupted job in its folder: its config
    (``--config-name eval``), its mode and overrides, and the checkpoint to go on from (training:
    the folder's ``last``; evaluation: the one it tests)."""
    try:
        name = HydraConfig.get().job.config_name or "config"
    except ValueError:  # composed outside a Hydra app
        name = "config"
    again = [o for o in overrides() if not o.startswith(("hydra.run.dir=", "ckpt_path=", "mode="))]
    resume = "ckpt_path=last" if cfg.mode == "train" else f"ckpt_path={ckpt}"
    head = "python -m dider.run" + ("" if name == "config" else f" --config-name {name}")
    return " ".join([head, f"mode={cfg.mode}", *again, f"hydra.run.dir={out_dir}", resume])


def overridden_keys() -> set[str]:
    """The config keys set on the command line (``+`` and ``~`` stripped), e.g.
    ``{"data.source.frame_rate"}``."""
    return {o.split("=", 1)[0].lstrip("+~") for o in overrides()}


# Settings that name no run (where it writes, what it logs to, how it shows progress) or that the
# name holds anyway.
UNNAMED = {"model", "seed", "experiment", "ckpt_path", "threads", "logger", "callbacks",
           "trainer.enable_progress_bar", "data.cache_dir", "data.source.root", "data.source.path"}


def run_label(cfg: DictConfig) -> str:
    """A run's name for TensorBoard (``--logdir_spec NAME:FOLDER``): the model, the seed and every
    other setting given on the command line, e.g. ``dider-seed1-model.num_edges=6``; no commas or
    colons, which logdir_spec reads as separators."""
    given = [o.lstrip("+~") for o in overrides()]
    given = [o for o in given if (key := o.split("=", 1)[0]) not in UNNAMED
             and not key.startswith(("hydra.", "logger.", "callbacks."))]
    name = "-".join([f"{cfg.model.get('name', 'model')}-seed{cfg.seed}", *given])
    return name.replace(",", ";").replace(":", ".")


def _data_name(cfg: DictConfig) -> str:
    """The data set's config name (``data=springs``), or where there is none (a config built in
    Python) its module's class."""
    if HydraConfig.initialized() and (name := HydraConfig.get().runtime.choices.get("data")):
        return str(name)
    return cfg.data._target_.rsplit(".", 1)[-1]


def hparams(cfg: DictConfig) -> dict[str, Any]:
    """The scalar settings worth comparing across runs, flattened with '/'."""
    keep = {"seed": cfg.seed, "model": cfg.model.get("name", "model"), "data": _data_name(cfg)}
    for section in ("protocol", "model", "data"):
        if section not in cfg:
            continue
        flat = OmegaConf.to_container(cfg[section], resolve=True)
        for key, value in _flatten(flat, section).items():
            if isinstance(value, (int, float, str, bool)) and not key.endswith("_target_"):
                keep[key] = value
    return keep


def hparams_tab(cfg: DictConfig) -> dict[str, Any]:
    """What TensorBoard's HParams table shows as columns: the model, the data, the seed, the number
    of edge types and every model and data setting given on the command line, so that the metrics
    are in view (all 63-71 settings pushed them off the screen; the other loggers get them all)."""
    every = hparams(cfg)
    given = {key.replace(".", "/") for key in overridden_keys()}
    return {k: v for k, v in every.items()
            if k in ("model", "data", "seed", "model/num_edges") or k in given}


def _flatten(d: Any, prefix: str) -> dict[str, Any]:
    if not isinstance(d, dict):
        return {prefix: d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_flatten(v, f"{prefix}/{k}"))
    return out


def format_table(metrics: dict[str, float]) -> str:
    width = max((len(k) for k in metrics), default=10)
    lines = [f"{'metric':<{width}}  value", f"{'-' * width}  ----------"]
    lines += [f"{k:<{width}}  {metrics[k]:.4g}" for k in leading_first(list(metrics))]
    return "\n".join(lines)


def log_results(loggers: list[Logger], cfg: DictConfig, metrics: dict[str, float],
                step: int) -> None:
    """A finished run's results in TensorBoard: the HParams entry (only finished runs enter it: no
    NaN rows of failed ones) and the results card in the text tab. The other loggers got the
    settings at the start."""
    for lg in loggers:
        if isinstance(lg, TensorBoardLogger):
            lg.log_hyperparams(hparams_tab(cfg),
                               metrics={k: metrics.get(k, math.nan) for k in hparam_metrics(cfg)},
                               step=step)
            card = results_markdown(metrics, f"{cfg.model.get('name', 'model')}, seed {cfg.seed}")
            lg.experiment.add_text("results", card, global_step=step)


def write_metrics(path: Path, cfg: DictConfig, metrics: dict[str, float], checkpoint: str | None,
                  checkpoint_version: str | None, objective: float | None,
                  provenance_: dict[str, Any]) -> None:
    """``metrics.json``: the test metrics, the overrides, seed and model, the checkpoint tested and
    the package version that wrote it (eval, resume), the objective, the provenance and the resolved
    config. A checkpoint in the run's folder is recorded relative to it, so the folder copied or
    moved still names its own."""
    if (checkpoint
        and (tested := Path(checkpoint).resolve()).is_relative_to(folder := path.parent.resolve())):
        checkpoint = str(tested.relative_to(folder))
    record = {
        "metrics": metrics,
        "mode": str(cfg.get("mode", "train")),
        "overrides": overrides(),
        "seed": int(cfg.seed),
        "model": cfg.model.get("name", "model"),
        "checkpoint": checkpoint,
        "checkpoint_version": checkpoint_version,
        "objective": objective,
        "provenance": provenance_,
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    atomic_write_text(path, json.dumps(record, indent=2, default=str))
