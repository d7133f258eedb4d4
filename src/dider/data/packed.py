"""Windows stored packed (:class:`PackedWindows`): one row per agent per window, window w owning rows
offsets[w]:offsets[w+1] (windows have different agent counts). A track source's cut gives them
(:class:`~dider.data.tracks.Tracks`); these join the scenes' windows and select some of them."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from dider.data.common import ragged_rows


@dataclass
class PackedWindows:
    """Windows cut from a source's scenes, raw (positions less the origin the cut was given, subtracted before any
    float32 rounding). P agent rows, W windows, T steps:

    - states [P, T, 4] float32 (x, y, vx, vy; zeros where absent), mask [P, T] bool (present);
    - offsets [W+1] long: window w owns rows offsets[w]:offsets[w+1], its agents by id;
    - agent [P] long: each row's agent id in the input (or a code into the tracks' ``names["agent"]``);
    - agent_class [P] long or None: codes into ``class_names`` (the sorted class names), None without classes;
    - start [W] long: the window's first step on its scene's grid of steps; scene [W] long: the index of its scene
      among the tracks' ``scenes``; frame [W] long: the input's frame of its step 0;
    - clip [W] long or None: each window's number among those of its set, once numbered (:meth:`numbered`).
    """

    states: torch.Tensor
    mask: torch.Tensor
    offsets: torch.Tensor
    agent: torch.Tensor
    start: torch.Tensor
    scene: torch.Tensor
    frame: torch.Tensor
    agent_class: torch.Tensor | None = None
    class_names: list[str] | None = None
    clip: torch.Tensor | None = None

    def __len__(self) -> int:
        return self.offsets.shape[0] - 1

    @classmethod
    def empty(cls, seq_len: int) -> PackedWindows:
        """No window of ``seq_len`` steps."""
        none = torch.zeros(0, dtype=torch.long)
        return cls(torch.zeros(0, seq_len, 4), torch.zeros(0, seq_len, dtype=torch.bool),
                   torch.zeros(1, dtype=torch.long), none, none, none, none)

    def numbered(self) -> PackedWindows:
        """The windows with ``clip`` [W] long: each window's number among these windows."""
        return replace(self, clip=torch.arange(len(self)))

    def select(self, idx: torch.Tensor) -> PackedWindows:
        """The windows ``idx`` [K] long, in that order (these windows themselves when ``idx`` keeps every one in
        order)."""
        if len(idx) == len(self) and bool((idx == torch.arange(len(idx))).all()):
            return self
        rows, offsets = ragged_rows(self.offsets, idx)
        pick = lambda t: None if t is None else t[idx]  # noqa: E731
        return PackedWindows(self.states[rows], self.mask[rows], offsets, self.agent[rows], self.start[idx],
                             self.scene[idx], self.frame[idx],
                             None if self.agent_class is None else self.agent_class[rows], self.class_names,
                             pick(self.clip))

    def shifted(self, origin: tuple[float, float]) -> PackedWindows:
        """The windows' positions less ``origin`` where agents are present (float32 states, cut at (0, 0))."""
        if origin == (0.0, 0.0):
            return self
        return replace(self, states=self.states - self.mask[..., None] * torch.tensor([*origin, 0.0, 0.0]))


def join(parts: Sequence[PackedWindows], seq_len: int) -> PackedWindows:
    """The windows of several parts (scenes, recordings) in order, as one set: rows and windows concatenated,
    offsets shifted, class codes remapped to the sorted union of the parts' class names (None where the parts have
    no classes). No part: no window of ``seq_len`` steps."""
    if not parts:
        return PackedWindows.empty(seq_len)
    shifts = torch.tensor([0, *(int(p.offsets[-1]) for p in parts)]).cumsum(0)
    offsets = torch.cat([torch.zeros(1, dtype=torch.long),
                         *(p.offsets[1:] + shift for p, shift in zip(parts, shifts[:-1], strict=True))])
    cat = lambda key: torch.cat([getattr(p, key) for p in parts])  # noqa: E731
    out = PackedWindows(cat("states"), cat("mask"), offsets, cat("agent"), cat("start"), cat("scene"), cat("frame"))
    if parts[0].class_names is None:
        return out
    names = sorted(set().union(*(p.class_names for p in parts)))
    lut = [torch.tensor([names.index(c) for c in p.class_names] or [0], dtype=torch.long) for p in parts]
    return replace(out, agent_class=torch.cat([m[p.agent_class] for m, p in zip(lut, parts, strict=True)]),
                   class_names=names)
