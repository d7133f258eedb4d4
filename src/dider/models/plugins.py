"""The four plugin seams of the relational VAE, as structural types: any module with these methods fits.

Shapes: B batch, T frames, N agents, D features, E = N(N-1) edges, K edge types, R LSTM width.
"""

from __future__ import annotations

from collections.abc import Mapping
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
    # The schedules' values given as tensors ({"kl_weight": ..., "tau": ...}; None: computed from step and total).
    # A step captured as a CUDA graph reads them from the device, where each replay finds the step's values.
    values: Mapping[str, torch.Tensor] | None = None

    def value(self, name: str, computed: float) -> float | torch.Tensor:
        """The schedule ``name`` at this progress: the given tensor where ``values`` holds it, else ``computed``."""
        return self.values[name] if self.values is not None and name in self.values else computed

    @property
    def fraction(self) -> float:
        """How much of training is done, in [0, 1] (1 when the run's length is unknown)."""
        return min(1.0, self.step / self.total) if self.total else 1.0

    def ramp_steps(self, fraction: float) -> int:
        """The optimiser steps that ``fraction`` of training spans (0 when the run's length is unknown)."""
        return int(fraction * self.total) if self.total else 0


# The network's plugin seams, by the key of the model config (``model.net.<seam>``) that picks each one's class.
SEAMS = ("encoder", "prior", "duration", "decoder")


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

    Optional capabilities, each a Protocol below, read once when the network is built
    (:class:`DurationCapabilities`): :class:`EarlyBoundary`, :class:`ObservedSpan`, :class:`ScoresCuts`,
    :class:`Annealed`, :class:`RetypesOnline`, :class:`HeldTypeSegments`. Where an edge enters, the roll-out's
    state machine reads a new type for every plugin and the duration runs on."""

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


class EarlyBoundary(Protocol):
    """A duration plugin whose segments may end before their duration runs out, online (a hazard's or a hold
    gate's boundary): the roll-out's state machine starts a new segment there."""

    def boundary(self, h_t: torch.Tensor, t: int, end: int) -> torch.Tensor:
        """h_t [B, E, R] at step t of ``end`` -> [B, E] bool, where a new segment starts at t."""
        ...


class ObservedSpan(Protocol):
    """A duration plugin that makes the burn-in one segment: transitions 0..observed-1 (0: none)."""

    observed: int


class ScoresCuts(Protocol):
    """A duration plugin that can score a given cut (``dider.analysis.diagnose``)."""

    def cut_kl(self, h_fwd: torch.Tensor, h_rev: torch.Tensor, gate: torch.Tensor, free: torch.Tensor,
               steps: torch.Tensor) -> torch.Tensor:
        """The duration KL of a posterior certain of the cut ``gate`` [B, E, T] bool over the ``free`` steps
        [B, E, T] bool, per present edge-step (steps [B]) -> [B]."""
        ...


class Annealed(Protocol):
    """A duration plugin with a soft-step temperature annealed over training (logged as ``schedule/tau``)."""

    def tau(self, progress: Progress) -> float | torch.Tensor: ...


class HeldTypeSegments(Protocol):
    """A duration plugin whose segments are runs of one type: its cut reads the posterior's type probabilities at
    each candidate start (``segment(..., types=[B, E, T, K])``), its prior hazard is fitted at every step to where
    the held type changes (``boundary_fit``), and online a boundary brings another type than the one held
    (``excludes_held``); its ``boundary`` reads the held type and the segment's age."""

    excludes_held: bool

    def boundary_fit(self, h_fwd: torch.Tensor, held: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """h_fwd [B, E, T, R], held [B, E, T] long, present [B, E, T] bool -> [B]."""
        ...


class RetypesOnline(Protocol):
    """A duration plugin whose online segments also end where the prior, after the burn-in, reads another type
    than the one held (when ``online_retype`` is true)."""

    online_retype: bool


@dataclass(frozen=True)
class DurationCapabilities:
    """What a duration plugin can do beyond :class:`Duration`, read once when the network is built."""

    boundary: bool = False  # EarlyBoundary
    observed: int = 0  # ObservedSpan's span (0 without one)
    cut_kl: bool = False  # ScoresCuts
    tau: bool = False  # Annealed
    online_retype: bool = False  # RetypesOnline, and on
    held_type: bool = False  # HeldTypeSegments

    @classmethod
    def of(cls, duration: object) -> DurationCapabilities:
        def has(interface: type) -> bool:
            return not missing_members(duration, interface)

        return cls(boundary=has(EarlyBoundary), observed=int(duration.observed) if has(ObservedSpan) else 0,
                   cut_kl=has(ScoresCuts), tau=has(Annealed),
                   online_retype=has(RetypesOnline) and bool(duration.online_retype),
                   held_type=has(HeldTypeSegments))


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


class KinematicDecoder(Protocol):
    """A decoder whose positions move by the predicted velocity through a step fitted to a training batch before
    the first optimiser step (``kinematic``: a :class:`~dider.models.decoders.KinematicStep`, or None: off)."""

    kinematic: Any


def missing_members(plugin: object, interface: type) -> list[str]:
    """The methods and attributes of a plugin ``interface`` that ``plugin`` lacks ([] when it fits)."""
    names = {n for n in vars(interface) if not n.startswith("_")} | set(vars(interface).get("__annotations__", {}))
    if "__call__" in vars(interface):
        names.add("__call__")
    return sorted(n for n in names if not hasattr(plugin, n))
