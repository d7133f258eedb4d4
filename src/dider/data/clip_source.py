"""What a clip source is (:class:`ClipSource`) and what it gives the data module: :class:`Clips`, a split of
fixed-length clips already cut (the simulators of :mod:`dider.data.simulators`, and the files that ship clips,
:mod:`dider.data.readers`: NRI's, DNRI's, the basketball sets, ``.npz`` trajectories)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Protocol

import torch


@dataclass
class Clips:
    """One split's clips, raw (not normalised). states: [S, T, N, 4] float32 (x, y, vx, vy; positions relative to
    ``origin``, the input's coordinates less it, taken off in float64 by the reader); mask: [S, T, N] bool or None
    (every agent present); edges: [S, T-1, E] long, the type of each transition t -> t+1, or None; ids: the clips'
    source identifiers ([S] or [S, N] long each) or None."""

    states: torch.Tensor
    mask: torch.Tensor | None = None
    edges: torch.Tensor | None = None
    ids: dict[str, torch.Tensor] | None = None
    origin: tuple[float, float] = (0.0, 0.0)

    def __len__(self) -> int:
        return self.states.shape[0]

    @property
    def present(self) -> torch.Tensor:
        """[S, T, N] bool: the mask, or every agent present."""
        return torch.ones(self.states.shape[:3], dtype=torch.bool) if self.mask is None else self.mask

    def select(self, idx: torch.Tensor) -> Clips:
        """The clips ``idx`` [K] long, in that order, ids and all."""
        pick = lambda t: None if t is None else t[idx]  # noqa: E731
        return Clips(self.states[idx], pick(self.mask), pick(self.edges),
                     None if self.ids is None else {k: v[idx] for k, v in self.ids.items()}, self.origin)

    def crop(self, steps: int) -> Clips:
        """Every clip's first ``steps`` steps (and the transitions between them)."""
        return Clips(self.states[:, :steps], None if self.mask is None else self.mask[:, :steps],
                     None if self.edges is None else self.edges[:, :steps - 1], self.ids, self.origin)

    def relative_to(self, origin: tuple[float, float]) -> Clips:
        """The clips' positions relative to ``origin`` (a trained model's): shifted by the small difference of the
        two origins, where agents are present."""
        if origin == self.origin:
            return self
        shift = torch.tensor([self.origin[0] - origin[0], self.origin[1] - origin[1], 0.0, 0.0], dtype=torch.float64)
        states = (self.states.double() + shift * self.present[..., None]).float()
        return Clips(states, self.mask, self.edges, self.ids, origin)


class ClipSource(Protocol):
    """A clip source as :class:`~dider.data.clips.ClipsDataModule` reads it: a class that a data config's
    ``data.source._target_`` names (dider's or one in a package of the user's own), its settings the node's other
    keys, best a frozen dataclass (what a checkpoint records of it: the fields). Optional members, read where
    present: ``predict_clips() -> Clips`` (every clip, for ``mode=predict``) and the class constants below."""

    GENERATED: ClassVar[bool]  # data.num_* are the sizes to simulate (else caps on what the files hold)
    FIT_ON_FILE: ClassVar[bool]  # the normaliser is fitted on the whole training file, before any cap
    SPLIT_SETTINGS: ClassVar[tuple[str, ...]]  # which of data.split, data.val_fraction and data.seed it reads
    UNITS: ClassVar[str]  # the positions' unit, for scale bars

    def clips(self, sizes: Mapping[str, int | None], cache_dir: Path) -> dict[str, Clips]:
        """The parts the input holds: ``train``, ``val`` and ``test``; ``train`` and ``test``; or ``all``."""
        ...

    def where(self) -> str:
        """What error messages name the input by (``data.source.root=...``)."""
        ...
