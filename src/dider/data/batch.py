"""The one batch format every data module yields, and min/max normalisation.

A batch is a plain dict (collates and moves between devices for free):
- ``states``: [B, T, N, 4] float, (x, y, vx, vy) normalised to [-1, 1] with train-split statistics.
- ``mask``:   [B, T, N] bool, agent present at that step.
- ``edges``:  [B, T-1, E] long (optional, synthetic data only): ground-truth type of each directed edge
  for the *transition* t -> t+1, i.e. the force that produced state t+1 from state t.
- ``pair_kind``: [B, E] long (optional, inD): 1 parked pair, 2 opposite-direction non-crossing pair, 0 other
  (:mod:`dider.data.pairs`), for the consistency check.
- ``source``: dict of long tensors (optional): where each clip came from in the input (clip index, scene,
  first frame, agent ids; :mod:`dider.data.common`).
- ``everyone``: a Python bool (optional): every agent present at every step of the batch, known where the batch
  was made, so that the model need not ask the device (a host synchronisation) to skip its masking passes.
"""

from __future__ import annotations

from typing import NotRequired, TypedDict

import torch


class Batch(TypedDict):
    states: torch.Tensor
    mask: torch.Tensor
    edges: NotRequired[torch.Tensor]
    pair_kind: NotRequired[torch.Tensor]
    source: NotRequired[dict[str, torch.Tensor]]
    everyone: NotRequired[bool]


class Normalizer:
    """Maps positions and velocities separately to [-1, 1] with scalar min/max (DNRI's scheme).

    Scalar (not per-axis) ranges keep the geometry isotropic, so distances stay comparable in x and y.

    "Raw" states (what :meth:`normalize` takes and :meth:`denormalize` gives, what data modules hold and metrics
    in data units read) are positions relative to ``origin`` (x0, y0), which the reader subtracted in float64
    before its float32 cast: tracks in UTM-sized coordinates (5e6 m) keep their centimetres, which float32 rounds
    to 0.5 m. :meth:`to_user` adds it back where positions leave (predictions, the explorer, the API).
    """

    def __init__(self, pos_range: tuple[float, float], vel_range: tuple[float, float],
                 origin: tuple[float, float] = (0.0, 0.0)) -> None:
        for name, (lo, hi) in {"pos_range": pos_range, "vel_range": vel_range}.items():
            if not hi > lo:
                raise ValueError(f"Normalizer {name}={(lo, hi)}: max must exceed min")
        self.pos_range = (float(pos_range[0]), float(pos_range[1]))
        self.vel_range = (float(vel_range[0]), float(vel_range[1]))
        self.origin = (float(origin[0]), float(origin[1]))

    @classmethod
    def fit(cls, states: torch.Tensor, mask: torch.Tensor | None = None,
            origin: tuple[float, float] = (0.0, 0.0)) -> Normalizer:
        """states: [..., N, 4] raw (relative to ``origin``); mask: [..., N] bool (present agents) or None."""
        flat = states.reshape(-1, 4)
        if mask is not None:
            flat = flat[mask.reshape(-1)]
        if flat.numel() == 0:
            raise ValueError("Normalizer.fit: no present agent states to fit on")
        pos, vel = flat[:, :2], flat[:, 2:]
        return cls((pos.min().item(), pos.max().item()), (vel.min().item(), vel.max().item()), origin)

    def to_user(self, states: torch.Tensor) -> torch.Tensor:
        """[..., 4] raw (e.g. :meth:`denormalize`'s) -> [..., 4] float64 in the user's coordinates."""
        states = states.double()
        if self.origin == (0.0, 0.0):
            return states
        return states + states.new_tensor([self.origin[0], self.origin[1], 0.0, 0.0])

    def _lo_span(self, ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        lo = torch.tensor([self.pos_range[0]] * 2 + [self.vel_range[0]] * 2, dtype=ref.dtype, device=ref.device)
        hi = torch.tensor([self.pos_range[1]] * 2 + [self.vel_range[1]] * 2, dtype=ref.dtype, device=ref.device)
        return lo, hi - lo

    def normalize(self, states: torch.Tensor) -> torch.Tensor:
        """[..., 4] raw -> [..., 4] in [-1, 1] on the fitting data."""
        lo, span = self._lo_span(states)
        return (states - lo) * (2.0 / span) - 1.0

    def denormalize(self, states: torch.Tensor) -> torch.Tensor:
        """[..., 4] normalised -> [..., 4] raw units."""
        lo, span = self._lo_span(states)
        return (states + 1.0) * (span / 2.0) + lo

    def state_dict(self) -> dict[str, tuple[float, float]]:
        return {"pos_range": self.pos_range, "vel_range": self.vel_range, "origin": self.origin}
