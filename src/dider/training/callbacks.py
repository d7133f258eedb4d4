"""Callbacks every training of the relational VAE runs with
(``RelationalVAEModule.configure_callbacks``): the forecast protocol checked against the clips,
evaluation that depends on the weights only, a guard that stops on NaN/inf naming where it came
from, and a checkpoint saved when the run is terminated."""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from collections.abc import Sequence
from typing import Any

import lightning as L
import torch
from lightning.pytorch.utilities.exceptions import SIGTERMException

from dider.protocol import check_horizons
from dider.training.rng import rng_state, set_rng_state

log = logging.getLogger(__name__)


class NonFiniteError(FloatingPointError):
    """A NaN/inf loss term or gradient during training: the message names the step, batch and
    term."""


class ProtocolFits(L.Callback):
    """Once the data are read, before any step: the model's burn-in and horizons must fit the clips
    it forecasts (validation's in a fit, the test's in a test), named by the protocol's keys.
    Training clips may be shorter (DNRI trains basketball on 40-step crops); prediction checks its
    own forecast length."""

    SPLITS = {"fit": ("val",), "validate": ("val",), "test": ("test",)}

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        steps, p = getattr(trainer.datamodule, "clip_steps", dict)(), pl_module.protocol
        for split in self.SPLITS.get(stage, ()):
            if split in steps:
                check_horizons(p.horizons, steps[split], p.burn_in, where=f", the {split} split's",
                               integers=True)


class EdgeLabelsFit(L.Callback):
    """Once the data are read, before any step: ground-truth edge labels must be types the model
    has. A label beyond ``model.num_edges`` has no row to score against (nor an oracle roll-out), so
    the run is refused here, naming the file, the largest label and the key, not after its last
    epoch (a test: every split of a fit, the test split of an evaluation)."""

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        dm, k = trainer.datamodule, pl_module.model.num_types
        for split, largest in getattr(dm, "largest_edge_label", dict)().items():
            if largest >= k and (stage == "fit" or split == stage):
                where = (dm.source.where() if hasattr(getattr(dm, "source", None), "where")
                         else "the data")
                fix = (f"set model.num_edges={largest + 1} or more to train and score against "
                       "these labels"
                       if stage == "fit" else "this model cannot score them (train one with "
                       f"model.num_edges={largest + 1} or more)")
                raise ValueError(f"{where}: the {split} split's edge labels go up to {largest}, "
                                 f"and the model has model.num_edges={k} types (0..{k - 1}): {fix}")


class EvalRandomState(L.Callback):
    """Validation, test and prediction draw (roll-out edge samples, hard Gumbel samples) from a
    generator seeded with ``seed``; the training run's random state is put back afterwards. Metrics
    are then a function of the weights, and checkpoints carry the training run's state, so a resumed
    run draws exactly what the uninterrupted one would have drawn."""

    CHECKPOINT_KEY = "dider_rng"

    def __init__(self, seed: int = 0) -> None:
        self.seed = seed
        # the training run's random state during evaluation
        self._outside: dict[str, Any] | None = None

    def _enter(self, *_: Any) -> None:
        if self._outside is None:
            self._outside = rng_state()
        torch.manual_seed(self.seed)

    def _exit(self, *_: Any) -> None:
        if self._outside is not None:
            set_rng_state(self._outside)
            self._outside = None

    on_validation_epoch_start = on_test_epoch_start = on_predict_epoch_start = _enter
    on_validation_epoch_end = on_test_epoch_end = on_predict_epoch_end = _exit

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule,
                           checkpoint: dict[str, Any]) -> None:
        checkpoint[self.CHECKPOINT_KEY] = self._outside or rng_state()

    def on_load_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule,
                           checkpoint: dict[str, Any]) -> None:
        if self.CHECKPOINT_KEY in checkpoint and trainer.state.fn == "fit":
            set_rng_state(checkpoint[self.CHECKPOINT_KEY])


class FiniteGuard(L.Callback):
    """Stops training with :class:`NonFiniteError` on a NaN/inf loss term or gradient, naming the
    step, the batch and the loss term: for a gradient, the step is replayed (same batch, same random
    state) and each term differentiated on its own. Costs one device sync per step for the loss and
    one for the gradients.

    ``every`` steps instead (None: on a GPU, the trainer's ``log_every_n_steps``; on a CPU, every
    step): the checks then accumulate on the device and are read back once per ``every`` steps, so a
    GPU's step never waits for them; the error names the first bad step, and the term is named by a
    rerun on a CPU.

    The module's ``training_step`` returns its loss terms (the objective's, ``loss`` and ``nelbo``)
    and offers ``loss_terms(batch)``, which recomputes them."""

    def __init__(self, every: int | None = None) -> None:
        self.every = every
        # batch, index, random state, where
        self._step: tuple[Any, int, dict[str, Any], str] | None = None
        self._loss_finite = True
        self._deferred: int | None = None  # the steps between read-backs, once training starts (None: each step)
        self._first_bad: torch.Tensor | None = None  # [2] long on the device: the first bad loss / gradient step
        self._count: torch.Tensor | None = None  # steps since the window's start, on the device
        self._window_start = 0

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        on_gpu = pl_module.device.type == "cuda"
        self._deferred = (self.every if self.every is not None
                          else (trainer.log_every_n_steps if on_gpu else None))
        if self._deferred is not None:
            self._reset(trainer, pl_module.device)

    def _reset(self, trainer: L.Trainer, device: torch.device) -> None:
        self._first_bad = torch.full((2,), -1, dtype=torch.long, device=device)
        self._count = torch.zeros((), dtype=torch.long, device=device)
        self._window_start = trainer.global_step

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any,
                             batch_idx: int) -> None:
        if self._deferred is not None:
            return
        where = f"step {trainer.global_step}, batch {batch_idx} of epoch {trainer.current_epoch}"
        self._step = (batch, batch_idx, rng_state(full=False), where)

    def _note(self, which: int, finite: torch.Tensor) -> None:
        """Deferred: record the window's first step where ``finite`` (a device bool) is false (0
        loss, 1 grads)."""
        first = self._first_bad[which]
        self._first_bad[which] = torch.where((first < 0) & ~finite, self._count, first)

    def on_before_backward(self, trainer: L.Trainer, pl_module: L.LightningModule,
                           loss: torch.Tensor) -> None:
        if self._deferred is not None:
            self._note(0, torch.isfinite(loss.detach()).all())
            return
        self._loss_finite = bool(torch.isfinite(loss.detach()).all())

    def on_after_backward(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # A non-finite loss is reported with its terms at the end of the batch; fp16 mixed precision
        # skips steps with inf gradients on purpose.
        if getattr(trainer.precision_plugin, "scaler", None) is not None:
            return
        named = [(k, p.grad) for k, p in pl_module.named_parameters() if p.grad is not None]
        if self._deferred is not None:
            if named:  # max |g| of each: finite exactly where every element is; a few fused launches, not two each
                largest = torch._foreach_norm([g for _, g in named], float("inf"))
                self._note(1, torch.isfinite(torch.stack(largest)).all())
            return
        if not self._loss_finite:
            return
        if not named or bool(torch.stack([torch.isfinite(g).all() for _, g in named]).all()):
            return
        params = [k for k, g in named if not bool(torch.isfinite(g).all())]
        msg = (f"non-finite gradient at {self._where()}: from loss term "
               f"{', '.join(self._culprits(trainer, pl_module))}; {len(params)} parameter(s) hit, "
               f"e.g. {params[:3]}; stopping the run")
        log.error(msg)
        raise NonFiniteError(msg)

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any,
                           batch: Any, batch_idx: int) -> None:
        if self._deferred is not None:
            self._count += 1
            if ((trainer.global_step - self._window_start) % self._deferred == 0
                    or batch_idx + 1 >= trainer.num_training_batches):
                self._read_back(trainer, pl_module)
            return
        if self._loss_finite or not isinstance(outputs, dict):
            return
        # the terms, then their weighted sum
        names = [*(k for k in outputs if k not in ("loss", "nelbo")), "loss"]
        values = torch.stack([outputs[k].detach().float() for k in names]).tolist()
        bad = {k: v for k, v in zip(names, values, strict=True) if not math.isfinite(v)}
        culprits = [k for k in bad if k != "loss"] or ["loss"]
        msg = (f"non-finite loss at {self._where()}: term {', '.join(culprits)} "
               f"({', '.join(f'{k}={v}' for k, v in bad.items())}); stopping the run")
        log.error(msg)
        raise NonFiniteError(msg)

    def _read_back(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Deferred: read the window's record (one host synchronisation) and stop on a bad step."""
        loss_at, grad_at = self._first_bad.tolist()
        for what, at in (("loss", loss_at), ("gradient", grad_at)):
            if at >= 0:
                msg = (f"non-finite {what} at step {self._window_start + at} (found at step "
                       f"{trainer.global_step}: the checks are read every {self._deferred} steps "
                       "on a GPU); stopping the run. To name the loss term, resume from the last "
                       "checkpoint before it on a CPU (trainer=cpu), which checks each step")
                log.error(msg)
                raise NonFiniteError(msg)
        self._reset(trainer, pl_module.device)

    def _where(self) -> str:
        return self._step[3] if self._step is not None else "unknown step"

    def _culprits(self, trainer: L.Trainer, pl_module: L.LightningModule) -> list[str]:
        """The loss terms whose own gradient is NaN/inf, from a replay of the last step."""
        if self._step is None:
            return ["unknown (no step to replay)"]
        batch, _, state, _ = self._step
        set_rng_state(state)
        params = [p for p in pl_module.parameters() if p.requires_grad]
        with torch.enable_grad(), trainer.precision_plugin.forward_context():
            terms = pl_module.loss_terms(batch)
        culprits = []
        for name in terms:
            if name == "loss" or not terms[name].requires_grad:
                continue
            grads = torch.autograd.grad(terms[name], params, retain_graph=True, allow_unused=True)
            if any(g is not None and not bool(torch.isfinite(g).all()) for g in grads):
                culprits.append(name)
        return culprits or ["loss (no single term: their sum)"]


class ResumeMidEpoch(L.Callback):
    """A run stopped mid-epoch (SIGTERM) resumes on the very batches the uninterrupted run would
    have trained on: a checkpoint saved inside an epoch carries the epoch's order (the training
    sampler's seed, :class:`~dider.data.common.EpochOrder`) and the batches done; on resume the data
    module's next training loader replays that order from the next batch. With the random state the
    checkpoint restores (:class:`EvalRandomState`) the resumed run gives the uninterrupted one's
    numbers."""

    CHECKPOINT_KEY = "dider_epoch_position"

    def __init__(self) -> None:
        self.done = 0  # batches of the current epoch trained

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any,
                           batch: Any, batch_idx: int) -> None:
        self.done = batch_idx + 1

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.done = 0

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule,
                           checkpoint: dict[str, Any]) -> None:
        order = getattr(getattr(trainer, "datamodule", None), "train_order", None)
        # Saved after a batch of the epoch and before its end (inside it, or in its validation): the
        # resumed run finishes the epoch in its order (maybe no batch left) with the saved random
        # state, so the next epoch draws its order as the uninterrupted run's did.
        inside = 0 < self.done <= trainer.num_training_batches
        if order is not None and order.seed is not None and inside:
            checkpoint[self.CHECKPOINT_KEY] = {"seed": order.seed, "done": self.done}
            # the epoch's logged means so far
            if (means := getattr(pl_module, "epoch_means", None)) is not None:
                checkpoint[self.CHECKPOINT_KEY]["means"] = means.state_dict()

    def on_load_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule,
                           checkpoint: dict[str, Any]) -> None:
        position = checkpoint.get(self.CHECKPOINT_KEY)
        dm = getattr(trainer, "datamodule", None)
        rng = checkpoint.get(EvalRandomState.CHECKPOINT_KEY, {}).get("torch")  # the training run's, at the save
        if position and rng is not None and trainer.state.fn == "fit" and hasattr(dm, "resume_position"):
            rng = torch.as_tensor(rng, dtype=torch.uint8).cpu()
            dm.resume_position = (int(position["seed"]), int(position["done"]), rng)
            self.done = int(position["done"])
            if "means" in position and hasattr(pl_module, "epoch_means"):
                pl_module.epoch_means.load_state_dict(position["means"])


class SaveOnTerminate(L.Callback):
    """On SIGTERM (a scheduler's time limit, ``kill``) or Ctrl-C (SIGINT, taken as SIGTERM),
    Lightning stops training with ``SIGTERMException``: save the run's state to the checkpoint
    folder's ``last.ckpt`` first, so ``ckpt_path=last`` resumes it (mid-epoch from the next batch:
    :class:`ResumeMidEpoch`). ``dider.run`` then exits non-zero.

    A SIGTERM during an epoch's validation waits for the validation to end (a validation is short
    beside a scheduler's grace period): its metrics, and the best checkpoints they pick, are then
    the uninterrupted run's. Stopped halfway, the resumed run could not validate that epoch again
    (Lightning resumes an evaluation from its next batch, the earlier batches' means lost)."""

    def __init__(self) -> None:
        self._deferred = False
        self._sigint: Any = None  # the SIGINT handler before this run's

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        # Ctrl-C as SIGTERM: the run stops at the next batch's end and saves; a second Ctrl-C
        # interrupts at once.
        if threading.current_thread() is threading.main_thread():
            self._sigint = signal.signal(signal.SIGINT, lambda *_: self._interrupt(trainer))

    def _interrupt(self, trainer: L.Trainer) -> None:
        trainer._signal_connector.received_sigterm = True
        signal.signal(signal.SIGINT, signal.default_int_handler)
        log.warning("Ctrl-C: stopping after this batch and saving (press it again to stop at once, "
                    "unsaved)")

    def teardown(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if self._sigint is not None and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self._sigint)
            self._sigint = None

    def on_validation_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule,
                                outputs: Any, batch: Any,
                                batch_idx: int, dataloader_idx: int = 0) -> None:
        # Lightning reads the flag right after this hook; it sets it again (and raises) once
        # validation is over.
        connector = trainer._signal_connector
        if trainer.state.fn == "fit" and not trainer.sanity_checking and connector.received_sigterm:
            connector.received_sigterm, self._deferred = False, True

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self._deferred:
            trainer._signal_connector.received_sigterm, self._deferred = True, False

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule,
                     exception: BaseException) -> None:
        folder = getattr(trainer.checkpoint_callback, "dirpath", None)
        if (not isinstance(exception, SIGTERMException) or folder is None
            or trainer.state.fn != "fit"):
            return
        path = f"{folder}/last.ckpt"
        trainer.save_checkpoint(path)
        log.error("terminated (SIGTERM or Ctrl-C) at epoch %d, step %d: saved %s",
                  trainer.current_epoch, trainer.global_step, path)


class EpochLine(L.Callback):
    """One log line per epoch, at its end (after its validation): the epoch, the training loss, the
    validation metrics named in ``metrics`` (those logged; a name ending in ``/*`` shows the last
    logged key under it, e.g. the longest horizon), the time spent and an estimate of the time left
    (from the epochs still to run, or ``trainer.max_time`` when that comes first). Through logging,
    so it shows in a log file and in output redirected to one, where a progress bar does not."""

    def __init__(self, metrics: tuple[str, ...] = ("train/loss_epoch", "val/nll", "val/select",
                                                   "val/mse/h01", "val/ade_vs_cv/*")) -> None:
        self.metrics = tuple(metrics)
        self.started = 0.0

    def _keys(self, logged: Sequence[str]) -> list[str]:
        keys = []
        for name in self.metrics:
            if name.endswith("/*"):
                keys += sorted((k for k in logged if k.startswith(name[:-1])),
                               key=lambda k: (len(k), k))[-1:]
            elif name in logged:
                keys.append(name)
        return keys

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.started, self.first_epoch = time.monotonic(), trainer.current_epoch

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not trainer.is_global_zero:
            return
        spent = time.monotonic() - self.started
        done = trainer.current_epoch + 1 - self.first_epoch
        logged = trainer.callback_metrics
        values = "  ".join(f"{k} {float(logged[k]):.4g}" for k in self._keys(list(logged)))
        left = ""
        if trainer.max_epochs and trainer.max_epochs > 0:
            rest = spent / done * (trainer.max_epochs - trainer.current_epoch - 1)
            if (limit := _time_remaining(trainer)) is not None:
                rest = min(rest, max(limit, 0.0))
            left = f", about {_clock(rest)} left"
        total = f"/{trainer.max_epochs}" if trainer.max_epochs and trainer.max_epochs > 0 else ""
        log.info("epoch %d%s  %s  (%s%s)", trainer.current_epoch + 1, total, values, _clock(spent), left)


def _time_remaining(trainer: L.Trainer) -> float | None:
    """Seconds left before ``trainer.max_time``, from the Timer callback Lightning adds for it (None without)."""
    from lightning.pytorch.callbacks import Timer

    timer = next((c for c in trainer.callbacks if isinstance(c, Timer)), None)
    return None if timer is None else timer.time_remaining()


def _clock(seconds: float) -> str:
    minutes, s = divmod(int(round(seconds)), 60)
    return f"{minutes}m{s:02d}s" if minutes else f"{s}s"


def every_run(eval_seed: int, check_finite: bool) -> list[L.Callback]:
    """The callbacks of every fit, test and prediction
    (``RelationalVAEModule.configure_callbacks``), in order: the data's checks before any step,
    evaluation's random state, the NaN/inf guard (``check_finite``), the mid-epoch resume and the
    checkpoint on termination."""
    guard = [FiniteGuard()] if check_finite else []
    return [ProtocolFits(), EdgeLabelsFit(), EvalRandomState(eval_seed), *guard, ResumeMidEpoch(), SaveOnTerminate()]
