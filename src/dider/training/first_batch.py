"""What is fitted to a training batch before the first optimiser step
(:meth:`RelationalVAEModule.on_fit_start`): a kinematic decoder's step
(:class:`~dider.models.decoders.KinematicStep`) and, with ``objective.nll.variance: fit``, the NLL's
variance per feature. A resumed run keeps its trained values (the weights are restored before the
hook, the step count after it: a checkpoint being loaded is the sign)."""

from __future__ import annotations

import logging
from typing import Any

import lightning as L
import torch

from dider.models.vae import RelationalVAE

log = logging.getLogger(__name__)


def fit_to_a_training_batch(model: RelationalVAE, trainer: L.Trainer, dm: Any,
                            device: torch.device) -> None:
    """model: the module's network; dm: the trainer's data module (None: fitted only where nothing
    needs it)."""
    step = model.decoder.kinematic if model.fits_kinematics else None
    likelihood = model.likelihood
    if (step is None and not likelihood.to_fit) or trainer.ckpt_path is not None:
        return
    if dm is None:
        if likelihood.to_fit:
            raise ValueError("model.net.objective.nll.variance=fit fits the variance to a training "
                             "batch of the data module: train through trainer.fit(model, "
                             "datamodule=...) or give a number")
        return
    # the loader's shuffling must not move the run's random state
    with torch.random.fork_rng(devices=[]):
        batch = next(iter(dm.train_dataloader()))
    states, mask = batch["states"].to(device), batch["mask"].to(device)
    # every rank fits its own batch; DDP needs one set of values: rank 0's (a broadcast tensor
    # arrives on rank 0's device, hence the moves)
    broadcast = trainer.strategy.broadcast
    if step is not None:
        step.fit(states, mask)
        slope, offset = (broadcast(torch.stack([step.slope.detach(), step.offset.detach()]))
                         .to(device))
        with torch.no_grad():
            step.slope.fill_(slope)
            step.offset.fill_(offset)
        if trainer.is_global_zero:
            log.info("kinematic step fitted on a training batch: slope %.4g, offset %.3g",
                     float(slope), float(offset))
    if likelihood.to_fit:
        likelihood.variance = broadcast(likelihood.fit(states, mask)).to(device)
        if trainer.is_global_zero:
            log.info("NLL variance fitted on a training batch, per feature: %s",
                     ", ".join(f"{v:.3g}" for v in likelihood.variance.tolist()))
