"""Hydra entry point: `python -m dider.run [overrides]` trains, tests and writes metrics.json."""

from __future__ import annotations

import json
import logging
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from lightning.fabric.plugins import CheckpointIO
from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint
from lightning.pytorch.loggers import Logger, TensorBoardLogger
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig, OmegaConf, open_dict

from dider.evaluation.passes import ForecastRequest
from dider.evaluation.scoring import cv_verdict, edges_verdict
from dider.io import atomic_write_text
from dider.outputs.prediction import PredictionWriter, PredictProgress
from dider.outputs.run_record import (
    format_table,
    hparams,
    in_sweep,
    log_results,
    overridden_keys,
    provenance,
    resume_command,
    run_dir_given,
    run_label,
    write_metrics,
)
from dider.outputs.summary import run_summary
from dider.outputs.viz import draw_figures
from dider.perf import compile_modules, tune_allocator
from dider.targets import class_path, named_targets
from dider.trained import TrainedModel, find_checkpoint, load, training_settings
from dider.training.building import module_parts
from dider.training.checkpoint import AtomicCheckpointIO
from dider.training.interrupt import drop_resumed_from, stop_on_signals
from dider.training.module import RelationalVAEModule
from dider.training.overrides import override_problem
from dider.training.preflight import check_monitors, clip_problem, input_warnings, validate_config
from dider.training.quiet import silence_library_chatter
from dider.training.run_lock import RunLock
from dider.training.runfolder import (
    RunRefused,
    check_checkpoint,
    check_fresh,
    clear_failed,
    close_run_log,
    eval_folder,
    is_rank_zero,
    log_failure,
    mark_failed,
    mark_refused,
    open_run_folder,
    predict_folder,
    resolve_ckpt,
    sweep_partial_writes,
)
from dider.validation import ConfigError

log = logging.getLogger(__name__)

def _build_list(group: DictConfig | None) -> list[Any]:
    return [instantiate(c) for c in (group or {}).values() if c is not None and "_target_" in c]


TERMINATED = 143  # the exit status of a run stopped by SIGTERM (128 + 15, as a shell reports it)

def trainer_plugins(cfg: DictConfig) -> list[Any]:
    """The trainer's plugins from ``trainer.plugins`` (if any), with atomic checkpoint writes unless a
    CheckpointIO is configured there."""
    plugins = [instantiate(p) if isinstance(p, DictConfig) else p for p in (cfg.trainer.get("plugins") or [])]
    if not any(isinstance(p, CheckpointIO) for p in plugins):
        plugins.append(AtomicCheckpointIO())
    return plugins


def predict(cfg: DictConfig) -> list[Path]:
    """mode=predict: the checkpoint's model (its own config and normaliser, whatever ``model=`` says) on every
    clip of ``data`` -> files under ``output_dir/predictions`` (:mod:`dider.outputs.prediction`). Returns them.

    The folder gets a training run's guarantees: ``predictions/`` must not exist yet (a refusal names it), a
    lock keeps a second live run out, and the files are written into a staging folder that becomes
    ``predictions/`` (with ``complete.json`` listing them) only once all are written: a killed prediction
    leaves no mix of two predictions' files."""
    validate_config(cfg)
    if cfg.predict.samples and not cfg.predict.forecast_steps:
        raise ConfigError(f"predict.samples={cfg.predict.samples}: sampled futures need predict.forecast_steps (how "
                          f"many steps to forecast)")
    started = time.time()
    apply_threads(cfg)
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    out_dir = predict_folder(Path(cfg.output_dir), _result_name(cfg, "predict"))
    with open_dict(cfg):
        cfg.output_dir = str(out_dir)
    final, staging = out_dir / "predictions", out_dir / ".predictions.partial"
    with RunLock(out_dir):  # first: a second prediction into the folder is refused before it does any work
        if final.exists() and is_rank_zero():
            raise RunRefused(f"{final} already holds a prediction; predict into another folder (hydra.run.dir=...)")
        names, writer = _predict_into(cfg, out_dir, final, staging, started)
    if names is None:
        return []
    written = [final / name for name in names]
    for path in written:
        print(f"predictions: {path}")
    if verdict := cv_verdict(writer.scores):
        (log.info if verdict[1] else log.warning)(verdict[0])
    return written


def _predict_into(cfg: DictConfig, out_dir: Path, final: Path, staging: Path, started: float
                  ) -> tuple[list[str] | None, PredictionWriter]:
    """The prediction itself, under the folder's lock: the names of the files written into ``staging`` and moved
    to ``final`` (None on a rank other than zero) and the writer (its forecast scores)."""
    ckpt = find_checkpoint(str(cfg.ckpt_path))  # a checkpoint file or a run folder, as dider.load takes
    trained = load(ckpt, trust=trusted(cfg))  # named errors for a foreign, older, damaged or unsafe checkpoint
    datamodule = _prediction_data(cfg, trained)
    burn_in = int(cfg.predict.burn_in or trained.config["protocol"]["burn_in"])
    steps, samples = cfg.predict.forecast_steps, int(cfg.predict.samples)
    module = RelationalVAEModule(  # the loaded model's network and config: the file is read (and checked) once
        **module_parts(trained.config, trained.trust, trained.network),
        forecast=ForecastRequest(burn_in, int(steps), samples) if steps else None)
    datamodule.prepare_data()  # the clips are read and checked before the trainer starts
    datamodule.setup("predict")
    clips = datamodule.datasets["predict"]
    where = " ".join(f"data.{k}={v}" for k in ("source.path", "source.root", "source.provider")
                     if (v := OmegaConf.select(cfg.data, k))) or "data"
    if problem := clip_problem(clips.states.shape[1], where, burn_in, cfg.predict.forecast_steps):
        raise ConfigError(problem)
    for warning in input_warnings(clips.states, clips.mask, trained.normalizer, where):
        log.warning(warning)
    open_run_folder(out_dir, cfg)
    shutil.rmtree(staging, ignore_errors=True)  # a killed prediction's files: never part of this one
    writer = PredictionWriter(staging, burn_in)
    progress = PredictProgress(cfg.predict.progress_s)
    trainer: L.Trainer = instantiate(cfg.trainer, callbacks=[writer, progress], logger=False,
                                     plugins=trainer_plugins(cfg))
    log.info("predicting %d clips with %s (model %s, trained with dider %s)", len(clips), ckpt,
             module.model.name, trained.version)
    try:
        trainer.predict(module, datamodule=datamodule, return_predictions=False)
    except SIGTERMException:
        shutil.rmtree(staging, ignore_errors=True)
        log.error("terminated (SIGTERM or Ctrl-C) before the predictions were complete: nothing written to %s", final)
        print(f"terminated (SIGTERM or Ctrl-C) before the predictions were complete: nothing written to {final}; "
              f"predict again with: {resume_command(cfg, out_dir, str(cfg.ckpt_path))}", file=sys.stderr)
        raise SystemExit(TERMINATED) from None
    if not trainer.is_global_zero:
        return None, writer
    names = [p.name for p in writer.written]
    atomic_write_text(staging / "complete.json", json.dumps({
        "files": names, "clips": len(clips), "checkpoint": str(ckpt), "checkpoint_version": trained.version,
        "provenance": provenance(started, str(trainer.strategy.root_device))}, indent=2))
    os.replace(staging, final)  # the complete set appears at once
    clear_failed(out_dir)
    return names, writer


def apply_threads(cfg: DictConfig) -> None:
    """``threads``: torch's intra-op threads for this process (null: torch's default)."""
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))


def _prediction_data(cfg: DictConfig, trained: TrainedModel) -> L.LightningDataModule:
    """The data module of ``mode=predict``: the settings that shape the features taken from the checkpoint
    where the command line does not set them (a differing one refused unless ``predict.force``), the
    checkpoint's normaliser."""
    take = _checkpoint_features(cfg, trained, "predict.force")
    with open_dict(cfg):
        for path, value in take.items():
            OmegaConf.update(cfg.data, path, value)
    datamodule = instantiate(cfg.data, _convert_="all")
    if not getattr(datamodule, "predicts", False):
        source = getattr(datamodule, "source", None)
        what = f"data.source._target_={class_path(type(source))}" if source is not None else type(datamodule).__name__
        raise ConfigError(f"data: {what} has no prediction set; mode=predict reads "
                          f"data=trajectories (npz), table (CSV/Parquet), soccer, dnri_files or ind/round/unid")
    datamodule.use_normalizer(trained.normalizer)
    return datamodule


def train(cfg: DictConfig) -> dict[str, float]:
    """Fit (mode=train) and test, or test a checkpoint (mode=eval). Returns the test metrics."""
    return fit_and_score(cfg)[0]


def fit_and_score(cfg: DictConfig) -> tuple[dict[str, float], float | None]:
    """:func:`train`, also returning ``optimized_metric``'s value (metrics.json's ``objective``)."""
    validate_config(cfg)
    started = time.time()
    apply_threads(cfg)
    out_dir = Path(cfg.output_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if not os.access(out_dir, os.W_OK):
        raise ConfigError(f"{out_dir}: the run folder is not writable (choose another hydra.run.dir)")
    trained, version = None, None
    ckpt = (str(eval_checkpoint(cfg.ckpt_path, out_dir)) if cfg.mode == "eval"
            else resolve_ckpt(cfg.ckpt_path, out_dir, run_dir_given()))
    if ckpt is not None:  # before any work: a checkpoint of another model fails naming both sides
        version = check_checkpoint(ckpt, OmegaConf.to_container(cfg.model, resolve=True))
    if cfg.mode == "eval":
        out_dir = eval_folder(out_dir, _result_name(cfg, "eval"))
        trained = load(ckpt, trust=trusted(cfg))  # named errors for a damaged, older or unsafe checkpoint, first
        with open_dict(cfg):  # every path of the run (checkpoints, logs, figures, exports) follows output_dir
            cfg.output_dir = str(out_dir)
            for path, value in _checkpoint_features(cfg, trained, "eval.force").items():
                OmegaConf.update(cfg.data, path, value)
        out_dir.mkdir(parents=True, exist_ok=True)
    with RunLock(out_dir):  # first: the folder checks below and the run never race another process
        if ckpt is None and is_rank_zero():
            check_fresh(out_dir)
        elif is_rank_zero():  # going on in the folder: what a killed write (checkpoint, figure) left is swept
            sweep_partial_writes(out_dir)
        open_run_folder(out_dir, cfg)
        return _fit_and_test(cfg, ckpt, out_dir, started, version, trained)


def trusted(cfg: DictConfig) -> tuple[str, ...]:
    """The classes of the user's own that a checkpoint's config may build (:mod:`dider.targets`): those ``trust``
    lists and those the run's own ``model`` config names (the user chose both)."""
    own = named_targets(OmegaConf.to_container(cfg.model, resolve=True))
    return tuple(sorted({*(cfg.get("trust") or ()), *own}))


def eval_checkpoint(ckpt_path: str | None, folder: Path) -> Path:
    """The checkpoint ``mode=eval`` tests: ``last`` (``folder``'s ``checkpoints/last.ckpt``), a checkpoint file, or
    a run folder (its best checkpoint, else its last, as :func:`dider.load` takes)."""
    if ckpt_path is None:
        raise ConfigError("mode=eval needs ckpt_path: a checkpoint file, a run folder, or last (this run folder's)")
    if str(ckpt_path) == "last":
        last = folder / "checkpoints" / "last.ckpt"
        if not last.is_file():
            raise FileNotFoundError(f"ckpt_path=last: no checkpoint found in {last.parent}")
        return last
    return find_checkpoint(str(ckpt_path))


def _result_name(cfg: DictConfig, mode: str) -> str:
    """The folder an evaluation or a prediction writes to in a run's folder (``eval/<name>``, ``predict/<name>``):
    ``eval.name`` / ``predict.name``, else the data config's name."""
    if cfg[mode].get("name"):
        return str(cfg[mode].name)
    try:
        return str(HydraConfig.get().runtime.choices.get("data") or "test")
    except ValueError:  # composed outside a Hydra app
        return "test"


def _checkpoint_features(cfg: DictConfig, trained: TrainedModel, force_key: str) -> dict[str, Any]:
    """The data settings that shape the features, taken from the checkpoint where the command line does not set
    them (a differing one refused, naming both, unless ``force_key`` is true): the keys whose value changes."""
    try:
        take = training_settings(trained, cfg.data, overridden_keys(), bool(OmegaConf.select(cfg, force_key)),
                                 force_key=force_key)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    for path, value in take.items():
        log.info("data.%s=%s: the checkpoint's (it shapes the features); data.%s=%s was the data config's",
                 path, value, path, OmegaConf.select(cfg.data, path))
    return take


def _fit_and_test(cfg: DictConfig, ckpt: str | None, out_dir: Path, started: float,
                  ckpt_version: str | None = None, trained: TrainedModel | None = None
                  ) -> tuple[dict[str, float], float | None]:
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    datamodule = instantiate(cfg.data, _convert_="all")  # plain lists: checkpoints stay weights_only-safe
    if trained is not None:  # an evaluation reads its clips as the checkpoint was trained to, never refitting
        datamodule.use_normalizer(trained.normalizer)
    model = RelationalVAEModule.from_config(cfg.model, cuda_graph=cfg.get("cuda_graph", False))
    if cfg.get("compile"):
        compile_modules(model.model)
    loggers: list[Logger] = _build_list(cfg.get("logger"))
    # The learning-rate monitor needs a logger to write to: without one (logger=none) it has nothing to do.
    callbacks = [c for c in _build_list(cfg.get("callbacks")) if loggers or not isinstance(c, LearningRateMonitor)]
    if cfg.mode == "train":
        check_monitors(model, cfg)
    trainer: L.Trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False,
                                     plugins=trainer_plugins(cfg))
    if trainer.world_size == 1:  # the data's problems (files, window lengths) surface before any training
        datamodule.prepare_data()
        datamodule.setup("fit" if cfg.mode == "train" else "test")
    for lg in loggers if trainer.is_global_zero else []:  # every logger gets the settings worth comparing
        if not isinstance(lg, TensorBoardLogger):  # TensorBoard's HParams entry waits for the results (below)
            lg.log_hyperparams(hparams(cfg))

    best = ""
    try:
        if cfg.mode == "train":
            trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt)
            best = next((c.best_model_path for c in callbacks if isinstance(c, ModelCheckpoint)), "")
            drop_resumed_from(ckpt, [c for c in callbacks if isinstance(c, ModelCheckpoint)])
        # verbose=False: the app prints the one final table itself (leading with the forecast in data units)
        trainer.test(model, datamodule=datamodule, ckpt_path=(best or None) if cfg.mode == "train" else ckpt,
                     verbose=False)
    except SIGTERMException:  # a SystemExit with status 0: schedulers and `&&` chains would see success
        print(f"terminated (SIGTERM or Ctrl-C); resume with: {resume_command(cfg, out_dir, ckpt)}", file=sys.stderr)
        raise SystemExit(TERMINATED) from None

    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("test/")}
    metrics |= getattr(trainer.lightning_module, "test_values", {})  # the test metrics unrounded (the log's float32)
    if trainer.is_global_zero:
        log_results(loggers, cfg, metrics, trainer.global_step)
    objective = _objective(cfg, trainer, callbacks, metrics)
    if trainer.is_global_zero:
        write_metrics(out_dir / "metrics.json", cfg, metrics, ckpt if cfg.mode == "eval" else (best or None),
                      ckpt_version, objective, provenance(started, str(trainer.strategy.root_device)))
        clear_failed(out_dir)  # an earlier attempt's record no longer describes the folder
        print(f"\n{format_table(metrics)}\n")
        if verdict := cv_verdict(metrics):
            (log.info if verdict[1] else log.warning)(verdict[0])
        if warning := edges_verdict(metrics):
            log.warning(warning)
        print(f"metrics: {out_dir / 'metrics.json'}", flush=True)
    try:
        with stop_on_signals():
            figures = draw_figures(trainer, model)  # after the results: a figure never costs them
    except SIGTERMException:
        log.error("terminated (SIGTERM or Ctrl-C) while drawing the figures; the results are complete (%s)",
                  out_dir / "metrics.json")
        print(f"terminated (SIGTERM or Ctrl-C) while drawing the figures (the results are written); draw them with: "
              f"{resume_command(cfg, out_dir, ckpt)}", file=sys.stderr)
        raise SystemExit(TERMINATED) from None
    if figures:
        # logdir_spec names the run in TensorBoard's HParams table (with --logdir it is the folder "tb")
        print(f"figures: {figures[0].parent}  (TensorBoard: tensorboard --logdir_spec {run_label(cfg)}:{out_dir})")
    if trainer.is_global_zero and (out_dir / "clips.npz").exists():
        print(f"explorer: python -m dider.analysis.explore {out_dir}  (writes {out_dir / 'explorer.html'})")
    if trainer.is_global_zero and metrics:
        data = HydraConfig.get().runtime.choices.get("data") if HydraConfig.initialized() else None
        print("\n" + run_summary(metrics, out_dir, str(cfg.model.get("name", "")), data,
                                 getattr(datamodule, "units", None)), flush=True)
    return metrics, objective


def _objective(cfg: DictConfig, trainer: L.Trainer, callbacks: list[Any], metrics: dict[str, float]) -> float | None:
    """``optimized_metric``'s value: the best checkpoint's score when the checkpoint callback monitors it
    (the value of the epoch whose weights were tested), else its last logged value; None if never logged."""
    name = cfg.get("optimized_metric")
    if not name:
        return None
    for c in callbacks:
        if isinstance(c, ModelCheckpoint) and c.monitor == name and c.best_model_score is not None:
            return float(c.best_model_score)
    value = metrics.get(name, trainer.callback_metrics.get(name))
    return None if value is None else float(value)


@hydra.main(version_base="1.3", config_path="pkg://dider.conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    """The app. Returns ``optimized_metric`` (a validation metric by default), which Hydra sweepers
    (e.g. the Optuna sweeper) minimise; never a test metric, so a search cannot tune on the test set."""
    silence_library_chatter()
    try:
        tune_allocator(cfg.get("allocator"))
        if cfg.mode == "predict":
            predict(cfg)
            objective = None
        else:
            objective = fit_and_score(cfg)[1]
    except Exception as e:  # into the run's own log and a failed.json beside it (a folder it took), then out
        log_failure(e)  # Hydra prints it on the console, once
        if is_rank_zero():
            mark_failed(Path(cfg.output_dir), e)
            mark_refused(Path(cfg.output_dir), e, sweep_job=in_sweep())
        raise
    finally:
        close_run_log()
    return objective if cfg.mode == "train" else None


def cli() -> None:
    """``python -m dider.run`` / ``dider-run``: the app, after a check that every override names a key (a moved or
    misspelt one is answered with the nearest keys, not with Hydra's "Could not override")."""
    if problem := override_problem(sys.argv[1:]):
        print(f"invalid configuration:\n  - {problem}", file=sys.stderr)
        raise SystemExit(2)
    main()


if __name__ == "__main__":
    cli()
