"""Training steps replayed from one CUDA graph (the top-level ``cuda_graph`` setting), for
:class:`~dider.training.module.RelationalVAEModule`.

With the setting on, the module optimises manually: each step's forward, loss and backward run as
one :class:`~dider.training.step_graph.StepGraph` (captured on a GPU, a dry run on a CPU), the
callbacks' backward hooks see the step's loss and gradients, and Lightning's optimiser wrapper takes
the update (so the step count, checkpoints and resume are Lightning's own). The schedules enter the
graph as device scalars, so an annealed weight moves at every replay.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping
from typing import Any, Protocol

import lightning as L
import torch
from lightning.pytorch.accelerators import CUDAAccelerator

from dider.models.plugins import Progress
from dider.training.step_graph import StepGraph


class TrainsOnBatches(Protocol):
    """What a graphed step needs of its LightningModule (structural: the module is not imported
    here)."""

    model: torch.nn.Module
    trainer: L.Trainer

    def train_values(self, batch: Any, progress: Progress) -> dict[str, torch.Tensor]: ...

    def optimizers(self) -> Any: ...

SETTING_VALUES = ("auto", True, False)


def unsupported(trainer: L.Trainer) -> list[str]:
    """The trainer settings a graphed step cannot keep (each as ``trainer.key=value``)."""
    out = []
    if trainer.gradient_clip_val:
        out.append(f"trainer.gradient_clip_val={trainer.gradient_clip_val}")
    if trainer.accumulate_grad_batches != 1:
        out.append(f"trainer.accumulate_grad_batches={trainer.accumulate_grad_batches}")
    if getattr(trainer.precision_plugin, "scaler", None) is not None:
        out.append(f"trainer.precision={trainer.precision}")
    if trainer.world_size > 1:
        out.append(f"trainer.devices={trainer.num_devices} (several processes)")
    return out


def wanted(setting: bool | str, trainer: L.Trainer | None) -> bool:
    """Whether a fit graphs its steps: ``True`` always (a dry run on a CPU), ``"auto"`` where
    training runs on a CUDA device and the trainer's settings allow it, ``False`` never."""
    if setting not in SETTING_VALUES:
        raise ValueError(f"cuda_graph={setting!r}: expected auto, true or false")
    if setting is False or trainer is None:
        return False
    problems = unsupported(trainer)
    if setting is True and problems:
        raise ValueError(f"cuda_graph=true cannot keep {', '.join(problems)}: set cuda_graph=false "
                         "or drop them")
    return setting is True or (isinstance(trainer.accelerator, CUDAAccelerator) and not problems)


class GraphedSteps:
    """A module's graphed training steps: ``step(batch, schedule)`` trains on one batch and returns
    its :meth:`~dider.training.module.RelationalVAEModule.train_values` (detached), having taken the
    optimiser step."""

    def __init__(self, module: TrainsOnBatches, warmup: int = 3) -> None:
        self.module = module
        self.graph = StepGraph(self._forward_backward, warmup)

    def _forward_backward(self, inputs: Mapping[str, torch.Tensor],
                          everyone: Hashable) -> dict[str, torch.Tensor]:
        """What the graph holds: the gradients' reset, the forward pass, the loss and the
        backward."""
        grads = [p.grad for p in self.module.model.parameters() if p.grad is not None]
        if grads:  # in place: the graph writes the gradients where the optimiser reads them
            torch._foreach_zero_(grads)
        batch: dict[str, Any] = {k: v for k, v in inputs.items() if not k.startswith("schedule/")}
        if everyone is not None:
            batch["everyone"] = everyone
        progress = Progress(values={k.removeprefix("schedule/"): v for k, v in inputs.items()
                                    if k.startswith("schedule/")})
        values = self.module.train_values(batch, progress)
        values["loss"].backward()
        return {k: v.detach() for k, v in values.items()}

    def step(self, batch: Mapping[str, Any],
             schedule: Mapping[str, float]) -> dict[str, torch.Tensor]:
        """batch: a training batch; schedule: the schedules' values at this step (host floats)."""
        module, trainer = self.module, self.module.trainer
        tensors = {k: v for k, v in batch.items() if isinstance(v, torch.Tensor)}
        out = self.graph(tensors, {f"schedule/{k}": float(v) for k, v in schedule.items()},
                         batch.get("everyone"))
        # what manual_backward would have called around the backward
        for callback in trainer.callbacks:
            callback.on_before_backward(trainer, module, out["loss"])
        for callback in trainer.callbacks:
            callback.on_after_backward(trainer, module)
        # Lightning's wrapper: counts the step, calls the optimiser hooks
        module.optimizers().step()
        return out
