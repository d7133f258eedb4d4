"""A run folder's guarantees: one live run at a time, no fresh run over an old one, checkpoints that
belong to the configured model, and a failed run that says so.

A folder "holds a run" when it has a ``metrics.json`` or a checkpoint. Training into it is allowed
only to resume it (``ckpt_path=last``); a lock file (``.dider.lock``, the writer's pid and host)
keeps a second live process out, and is taken over when its writer is gone.
"""

from __future__ import annotations

import importlib
import inspect
import json
import logging
import os
import traceback
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from dider.io import atomic_write_text
from dider.models.checkpoint_format import network_config, read
from dider.models.plugins import SEAMS
from dider.training.preflight import version_problem
from dider.validation import ConfigError

log = logging.getLogger(__name__)

def is_rank_zero() -> bool:
    """False in the extra processes a DDP launcher starts (they run the app again with RANK set)."""
    return os.environ.get("RANK", os.environ.get("LOCAL_RANK", "0")) == "0"


def holds_run(folder: Path) -> list[str]:
    """What in ``folder`` shows an earlier run: ``metrics.json`` and checkpoint names ([] for
    none)."""
    found = ["metrics.json"] if (folder / "metrics.json").exists() else []
    return found + sorted(f"checkpoints/{p.name}" for p in (folder / "checkpoints").glob("*.ckpt"))


def check_fresh(folder: Path) -> None:
    """A fresh training run must not mix its files with an earlier run's (a later ``ckpt_path=last``
    would resume the wrong one)."""
    if found := holds_run(folder):
        raise RunRefused(f"{folder} already holds a run ({', '.join(found[:3])}): resume it with "
                         "ckpt_path=last, or train into another folder (hydra.run.dir=...)")


def resolve_ckpt(ckpt_path: str | None, folder: Path, folder_given: bool) -> str | None:
    """``last``: this run folder's ``checkpoints/last.ckpt`` (after a kill during its first write,
    the newest complete checkpoint there). Absent, a fresh start only where that is clearly meant
    (the folder was named on the command line: a restartable job's first start), with a notice; in a
    new timestamped folder resuming can never work, so that is an error naming where it looked (the
    temporary files of killed writes are removed once the folder's lock is taken:
    :func:`sweep_partial_writes`)."""
    if ckpt_path is None:
        return None
    if ckpt_path != "last":
        if not Path(ckpt_path).is_file():
            raise FileNotFoundError(f"ckpt_path={ckpt_path}: no such checkpoint file")
        return ckpt_path
    last = folder / "checkpoints" / "last.ckpt"
    if last.exists():
        return str(last)
    if (newest := newest_checkpoint(last.parent)) is not None:
        log.warning("ckpt_path=last: %s is missing (a run killed while writing its first one); "
                    "resuming from the newest complete checkpoint, %s", last, newest)
        return str(newest)
    if not folder_given:
        raise FileNotFoundError(f"ckpt_path=last: no checkpoint in {last.parent}, a new run "
                                "folder; name the run to resume with hydra.run.dir=THAT_RUN "
                                "(ckpt_path=last looks in the run's own folder)")
    log.warning("ckpt_path=last: no checkpoint in %s yet: starting a fresh run there", last.parent)
    return None


def sweep_partial_writes(folder: Path) -> None:
    """Remove the temporary files that a process killed while writing (a checkpoint, a figure, a
    record) left anywhere in the run folder ``folder`` (:func:`dider.io.atomic_write` names them
    ``.<name>.<random>.tmp``). Call it holding the folder's lock: a live writer's file is never one
    of them."""
    for tmp in folder.rglob(".*.tmp"):
        if tmp.is_file() and not tmp.is_symlink():
            log.warning("%s: removing the temporary file of a write that never finished", tmp)
            tmp.unlink(missing_ok=True)


def newest_checkpoint(folder: Path) -> Path | None:
    """The checkpoint in ``folder`` with the most optimiser steps (a readable one; None if there is
    none)."""
    best: tuple[int, Path] | None = None
    for path in folder.glob("*.ckpt"):
        try:
            step = int(read(path, mmap=True).get("global_step", -1))
        except Exception:  # a damaged or foreign file is no candidate  # noqa: BLE001
            continue
        if best is None or step > best[0]:
            best = (step, path)
    return None if best is None else best[1]


def predict_folder(folder: Path, name: str) -> Path:
    """Where ``mode=predict`` writes (its ``predictions/``, ``.hydra/`` and ``run.log``): ``folder``
    itself, unless it holds a run (checkpoints or a ``metrics.json``), whose record a prediction
    never replaces: then ``folder/predict/<name>``."""
    held = any((folder / "checkpoints").glob("*.ckpt")) or (folder / "metrics.json").exists()
    return folder / "predict" / name if held else folder


def eval_folder(folder: Path, name: str) -> Path:
    """Where ``mode=eval`` writes its results: ``folder`` itself, unless it holds a training run
    (checkpoints, or a training's ``metrics.json``), whose results an evaluation never replaces:
    then ``folder/eval/<name>``. A folder that already holds an evaluation is refused, as a second
    training is."""
    trained = any((folder / "checkpoints").glob("*.ckpt")) or recorded_mode(folder) == "train"
    target = folder / "eval" / name if trained else folder
    if (target / "metrics.json").exists():
        raise RunRefused(f"{target} already holds an evaluation (metrics.json): evaluate into "
                         "another folder (eval.name=OTHER, or hydra.run.dir=...)")
    return target


def recorded_mode(folder: Path) -> str | None:
    """The ``mode`` a folder's ``metrics.json`` records (None: no readable record)."""
    try:
        record = json.loads((folder / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict):
        return None
    config = record.get("config")
    return record.get("mode") or (config.get("mode") if isinstance(config, dict) else None)


def _flat(node: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(node, Mapping):
        return {prefix: node}
    out: dict[str, Any] = {}
    for k, v in node.items():
        out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def shape_settings(model: Mapping[str, Any]) -> dict[str, Any]:
    """The settings of a model config that fix its parameter shapes (name, num_edges, each plugin's
    target, its integer sizes and the other settings its class names in ``SHAPES``), flattened with
    dots."""
    flat = _flat({k: model.get(k) for k in ("name", "num_edges", *SEAMS)})
    shaped = {f"{plugin}.{name}" for plugin in SEAMS
              for name in getattr(_plugin_class(flat, plugin), "SHAPES", ())}
    out = {k: v for k, v in flat.items() if k in ("name", "num_edges") or k.endswith("_target_")
           or (isinstance(v, int) and not isinstance(v, bool)) or k in shaped}
    # a named setting the config leaves out is its constructor's default
    return out | {k: signature_default(flat, k) for k in shaped - set(out)}


def _plugin_class(flat: Mapping[str, Any], plugin: str) -> type | None:
    """The class of ``plugin`` (``encoder``) named by ``flat``'s ``<plugin>._target_``; None where
    there is none."""
    target = flat.get(f"{plugin}._target_")
    if not isinstance(target, str) or "." not in target:
        return None
    module, _, cls = target.rpartition(".")
    try:
        return getattr(importlib.import_module(module), cls)
    except (ImportError, AttributeError):
        return None


def signature_default(flat: Mapping[str, Any], key: str) -> Any:
    """The default that the plugin owning ``key`` (``decoder.prediction_steps``) gives it in its
    constructor, the plugin's class read from ``flat``'s ``<plugin>._target_``; None where there is
    none."""
    plugin, _, name = key.rpartition(".")
    cls = _plugin_class(flat, plugin)
    if cls is None:
        return None
    try:
        param = inspect.signature(cls.__init__).parameters.get(name)
    except (TypeError, ValueError):
        return None
    return None if param is None or param.default is inspect.Parameter.empty else param.default


def check_checkpoint(path: str, model: Mapping[str, Any]) -> str:
    """Fail before any work when ``path`` is not a training checkpoint, or one of another model than
    the config's: the error names each differing setting with both values. Warns when another minor
    or major version wrote it. -> the package version it records ("" for none)."""
    try:
        ckpt = read(path, f"ckpt_path={path}", mmap=True)
    except ValueError as e:  # unreadable, not a training checkpoint, or of another format
        raise ConfigError(str(e)) from e
    saved = (ckpt["hyper_parameters"].get("net") if isinstance(ckpt["hyper_parameters"], Mapping)
             else None)
    if not isinstance(saved, Mapping):
        raise ConfigError(f"ckpt_path={path}: not a dider training checkpoint (no model config in "
                          "its hyper-parameters)")
    mine, theirs = shape_settings(network_config(model)), shape_settings(saved)
    # a setting added to a plugin after the checkpoint was written is, there, its constructor's
    # default
    theirs |= {k: signature_default(theirs, k) for k in set(mine) - set(theirs)}
    key = lambda k: (f"model.{k}" if k in ("name", "num_edges")  # noqa: E731 (as users set it)
                     else f"model.net.{k}")
    changed = [k for k in sorted(set(mine) | set(theirs)) if mine.get(k) != theirs.get(k)]
    if changed:
        fix = (f"pass the model it was trained with, e.g. model={theirs.get('name')}"
               if mine.get("name") != theirs.get("name")
               else "pass its settings: " + " ".join(f"{key(k)}={theirs.get(k)}" for k in changed))
        raise ConfigError(f"ckpt_path={path} holds another model than the config's ({fix}):\n  - "
                          + "\n  - ".join(
                              f"{key(k)}: checkpoint {theirs.get(k)!r}, config {mine.get(k)!r}"
                              for k in changed))
    version = str((ckpt.get("dider") or {}).get("version", ""))
    if warning := version_problem(version):
        log.warning("ckpt_path=%s: %s", path, warning)
    return version


class RunRefused(ConfigError):
    """The run folder belongs to another run (finished, live, or a complete prediction): nothing is
    written into it, not even a failure record."""


def open_run_folder(folder: Path, cfg: Mapping[str, Any] | None = None) -> None:
    """Once the folder checks have passed (never before: a refused run leaves another run's folder
    as it was): Hydra's record of the run (``.hydra/config.yaml``, ``hydra.yaml``,
    ``overrides.yaml``, as ``dider.analysis.report`` reads them) and the run's log file ``run.log``,
    on rank zero. A folder holding a symbolic link is refused first."""
    if not is_rank_zero():
        return
    if links := [f"{p} -> {os.readlink(p)}" for p in sorted(folder.iterdir()) if p.is_symlink()]:
        # a planted link would send the run's writes (its log, records, checkpoints, predictions)
        # outside the folder
        raise RunRefused(f"{folder}: holds link(s) {links}; dider writes the files of its run "
                         "folder itself and follows no link it did not make: remove them, or use "
                         "another hydra.run.dir")
    OPENED.add(folder.resolve())
    try:
        hydra = HydraConfig.get()
    except ValueError:  # composed outside a Hydra app (tests, the Python API): no record to write
        hydra = None
    if hydra is not None and cfg is not None:
        record = folder / ".hydra"
        task = (OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
                if isinstance(cfg, DictConfig) else cfg)
        atomic_write_text(record / "config.yaml", OmegaConf.to_yaml(task))
        atomic_write_text(record / "hydra.yaml", OmegaConf.to_yaml({"hydra": hydra}))
        atomic_write_text(record / "overrides.yaml", OmegaConf.to_yaml(list(hydra.overrides.task)))
    close_run_log()  # one run's log at a time (a process may run several: tests, the Python API)
    handler = logging.FileHandler(folder / "run.log", delay=True)
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    logging.getLogger().addHandler(handler)
    _LOG.append(handler)


def log_failure(error: BaseException) -> None:
    """The error and its traceback into the run's log file only: the console already gets it once,
    from Hydra."""
    record = logging.LogRecord(__name__, logging.ERROR, __file__, 0, "run failed: %s", (error,),
                               (type(error), error, error.__traceback__))
    for handler in _LOG:
        handler.handle(record)


def close_run_log() -> None:
    """Detach and close the run log :func:`open_run_folder` attached, if any."""
    while _LOG:
        handler = _LOG.pop()
        logging.getLogger().removeHandler(handler)
        handler.close()


_LOG: list[logging.Handler] = []
# the folders this process has taken (open_run_folder): only those get a failed.json
OPENED: set[Path] = set()
LOG_FORMAT = "[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"  # Hydra's console format


def mark_failed(folder: Path, error: BaseException) -> None:
    """``folder/failed.json``: the error and its traceback, so a failed run's folder explains
    itself; only in a folder this process has taken (:func:`open_run_folder`), never in one it
    refused."""
    if folder.resolve() not in OPENED:
        return
    _write_failed(folder, error)


def _write_failed(folder: Path, error: BaseException) -> None:
    """``failed.json`` in ``folder``; a write that fails too (a full disk) is only warned about: the
    run's own error stays the one reported."""
    text = "".join(traceback.format_exception(error))
    try:
        atomic_write_text(folder / "failed.json", json.dumps({"status": "failed",
                                                              "error": repr(error),
                                                              "traceback": text}, indent=2))
    except OSError as e:
        log.warning("could not record the failure in %s (%s); the error follows",
                    folder / "failed.json", e)


def mark_refused(folder: Path, error: BaseException, sweep_job: bool) -> None:
    """A run refused before it took its folder (its config, say), where the folder is still empty
    (made for this run by Hydra): a sweep's job folder gets ``failed.json`` with the reason
    (``report`` then says why, not "missing"); a single run's is removed, so a refusal leaves
    nothing behind. A folder with anything in it is another run's, left as it was."""
    try:
        if folder.resolve() in OPENED or any(folder.iterdir()):
            return
        if sweep_job:
            _write_failed(folder, error)
        else:
            folder.rmdir()
    except OSError:  # gone, or not ours to change
        return


def clear_failed(folder: Path) -> None:
    """A run that succeeded in ``folder`` removes an earlier attempt's ``failed.json``, which no
    longer describes it."""
    (folder / "failed.json").unlink(missing_ok=True)
