"""The four plugin seams of the relational VAE, as structural types: any module with these methods fits.

Shapes: B batch, T frames, N agents, D features, E = N(N-1) edges, K edge types, R LSTM width.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import torch

from dider.models.encoder import EncoderOutput
from dider.models.segments import Segmentation


@dataclass(frozen=True)
class Progress:
    """Where training stands, for the annealed schedules (KL warm-up, capacities, soft-step temperature).

    ``total`` unknown (None: outside a Trainer, or an unbounded run) puts the fraction-of-training schedules
    at their end values, which is also what a trained model uses.
    """

    step: int = 0  # optimiser steps taken
    total: int | None = None  # optimiser steps in the whole run

    @property
    def fraction(self) -> float:
        """How much of training is done, in [0, 1] (1 when the run's length is unknown)."""
        return min(1.0, self.step / self.total) if self.total else 1.0

    def ramp_steps(self, fraction: float) -> int:
        """The optimiser steps that ``fraction`` of training spans (0 when the run's length is unknown)."""
        return int(fraction * self.total) if self.total else 0


class Encoder(Protocol):
    """Per-edge features: a teacher-forced pass over a whole clip, and the forward (past-only) LSTM alone,
    over given frames or one frame at a time for roll-outs."""

    def __call__(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> EncoderOutput:
        """x [B, T, N, D], mask [B, T, N] or None -> features of the T-1 transitions."""
        ...

    def past(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> tuple[torch.Tensor, Any]:
        """x [B, T, N, D] -> h_fwd [B, E, T, R] and the recurrent state after frame T-1."""
        ...

    def step(self, x_t: torch.Tensor, state: Any, mask_t: torch.Tensor | None = None) -> tuple[torch.Tensor, Any]:
        """x_t [B, N, D] -> h_fwd_t [B, E, R] and the new state."""
        ...


class Prior(Protocol):
    """Edge-type logits from the forward LSTM state: h [..., R] -> [..., K]."""

    def __call__(self, h_fwd: torch.Tensor) -> torch.Tensor: ...


class Duration(Protocol):
    """How each edge's time axis is cut into segments of one type.

    Optional: ``boundary(h_t, t, end) -> [B, E] bool``, where a segment ends early online (the roll-out's state
    machine starts a new one there as when its duration runs out; a hold gate's is the only one). Where an edge
    enters, the state machine reads a new type for every plugin and the duration runs on."""

    def segment(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, x: torch.Tensor,
                progress: Progress = Progress(), present: torch.Tensor | None = None) -> Segmentation:
        """Whole-clip segmentation for training and posterior inference: h_fwd, h_rev [B, E, T, R], present
        [B, E, T] bool (edges present at each step) or None (all are). A slot should start where an edge
        enters (``Segmentation.split_at`` splits one there): a slot's type is read, and its edge KL counted,
        at its first step."""
        ...

    def next_duration(self, h_t: torch.Tensor, t: int, end: int) -> torch.Tensor:
        """Online: an edge whose segment ended at step t starts one lasting [B, E] long steps (past only)."""
        ...


class Decoder(Protocol):
    """One-step predictions of every agent's next state given the edge types."""

    stateless: bool  # True: a prediction depends on the current frame only (no recurrent state)

    def __call__(self, x: torch.Tensor, z: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Teacher-forced: x [B, T, N, D], z [B, T, E, K] -> predictions of the next frames [B, T, N, D]."""
        ...

    def init_state(self, batch: int, num_agents: int, ref: torch.Tensor) -> Any: ...

    def step(self, x_t: torch.Tensor, z_t: torch.Tensor, state: Any,
             mask_t: torch.Tensor | None = None) -> tuple[torch.Tensor, Any]:
        """x_t [B, N, D], z_t [B, E, K] -> the next frame [B, N, D] and the new state."""
        ...


def missing_members(plugin: object, interface: type) -> list[str]:
    """The methods and attributes of a plugin ``interface`` that ``plugin`` lacks ([] when it fits)."""
    names = {n for n in vars(interface) if not n.startswith("_")} | set(vars(interface).get("__annotations__", {}))
    if "__call__" in vars(interface):
        names.add("__call__")
    return sorted(n for n in names if not hasattr(plugin, n))
