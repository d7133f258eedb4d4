"""Segmentations of each edge's time axis into slots that each hold one edge type.

Shapes: B batch, E edges, T steps (transitions), S slots, K edge types.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch


def _einsum_fp32(equation: str, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``einsum`` outside autocast: the slot sums hold logits, probabilities and the boundaries'
    gradients, which bf16 would round (the operands are small: [B, E, T, S] and [B, E, S, K])."""
    with torch.autocast(a.device.type, enabled=False):
        return torch.einsum(equation, a.float(), b.float())


def _pool_ahead(values: torch.Tensor, starts: torch.Tensor) -> torch.Tensor:
    """values [B, E, T, F], starts [B, E, T] bool -> [B, E, T, F]: at each step t, the mean of
    values over t up to the first start after t (or the end), in fp32."""
    t = values.shape[2]
    step = torch.arange(t, device=values.device)
    # the first start at or after t
    ahead = torch.where(starts, step, t).flip(-1).cummin(-1).values.flip(-1)
    nxt = torch.nn.functional.pad(ahead[..., 1:], (0, 1), value=t)  # ... strictly after t
    v = values.float()
    # [B, E, T+1, F]: sum over t' >= t
    tail = torch.nn.functional.pad(v.flip(2).cumsum(2).flip(2), (0, 0, 0, 1))
    index = nxt.unsqueeze(-1).expand(*nxt.shape, v.shape[-1])
    return (tail[:, :, :t] - tail.gather(2, index)) / (nxt - step).unsqueeze(-1).to(v.dtype)


def entries(present: torch.Tensor) -> torch.Tensor:
    """[..., T] bool, an edge present at each step -> [..., T] bool: where it enters, present after
    a step without it (never at step 0, where every segmentation starts anyway)."""
    return present & ~torch.nn.functional.pad(present[..., :-1], (1, 0), value=True)


def forced_boundaries(t: int, observed: int, device: torch.device,
                      present: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Steps whose boundary no plugin chooses, and whether a segment starts there: [T] bool each, or
    [B, E, T] with ``present`` [B, E, T] bool. A segment starts at step 0, at ``observed`` (the
    first forecast transition, when the burn-in is one observed segment; 0: none) and where an edge
    enters; none inside the burn-in or where the edge is absent."""
    step = torch.arange(t, device=device)
    fixed, value = step <= observed, (step == 0) | (step == observed)
    if present is None:
        return fixed, value
    entered = entries(present)
    # step 0 opens the first slot even when absent
    value = (value | entered) & (present | (step == 0))
    return fixed | entered | ~present, value


@dataclass
class Segmentation:
    start: torch.Tensor  # [B, E, S] long: first step of each slot
    valid: torch.Tensor  # [B, E, S] bool: the slot holds at least one step
    # [B, E, T, S] one-hot step -> slot (straight-through); None: slot s is step s
    assign: torch.Tensor | None
    kl: torch.Tensor  # [B] KL of the duration latents (zero for plugins without one)
    # [] mean std of the duration latents, for monitoring
    sigma: torch.Tensor | None = field(default=None)
    # [B, E, S] float: 1 forward for the slots that hold steps, with the gradient of the boundary
    # that opens them (straight-through), so a slot's edge KL reaches its boundary; None: ``valid``,
    # no gradient.
    weight: torch.Tensor | None = field(default=None)
    # [B, E, T] bool (or broadcastable): steps whose boundary the plugin does not choose (the clip's
    # first step, the burn-in, where an edge enters or is absent); None: the first step only.
    fixed: torch.Tensor | None = field(default=None)

    def free(self, present: torch.Tensor) -> torch.Tensor:
        """[B, E, T] bool: the present steps where the plugin chooses whether a segment starts
        (``present`` [B, E, T] bool)."""
        fixed = (torch.zeros_like(present)
                 .index_fill(-1, torch.tensor([0], device=present.device), True)
                 if self.fixed is None else self.fixed)
        return present & ~fixed

    @property
    def num_steps_per_slot(self) -> torch.Tensor:
        """[B, E, S] float: steps in each slot (the number of steps when ``assign`` is None)."""
        if self.assign is None:
            return self.valid.to(torch.float32)
        return self.assign.detach().sum(dim=2)

    @property
    def slot_weight(self) -> torch.Tensor:
        """[B, E, S] float: what each slot's edge KL is counted with, ``weight`` or else
        ``valid``."""
        return self.valid.to(torch.float32) if self.weight is None else self.weight

    def gather(self, values: torch.Tensor) -> torch.Tensor:
        """Read per-step values at each slot's first step: [B, E, T, F] -> [B, E, S, F]."""
        if self.assign is None:
            return values
        index = self.start.unsqueeze(-1).expand(*self.start.shape, values.shape[-1])
        return values.gather(2, index)

    def pool(self, values: torch.Tensor) -> torch.Tensor:
        """Mean of per-step values over each slot's steps: [B, E, T, F] -> [B, E, S, F] (0 for empty
        slots).

        Where slot s is the segment starting at step s (a boundary-based plugin: ``weight`` set),
        slot s holds, whether or not a segment starts there, the mean over s up to the next start
        after it: for a segment its own steps, and elsewhere the type a segment starting there would
        hold, which is what a boundary's straight-through gradient compares with the type held
        before it."""
        if self.assign is None:
            return values
        if self.weight is not None:
            return _pool_ahead(values, self.valid)
        total = _einsum_fp32("bets,betf->besf", self.assign, values)
        return total / self.assign.sum(2).unsqueeze(-1).clamp_min(1.0)

    def spread(self, per_slot: torch.Tensor) -> torch.Tensor:
        """Hold each slot's value over its steps: [B, E, S, F] -> [B, E, T, F]."""
        if self.assign is None:
            return per_slot
        return _einsum_fp32("bets,besf->betf", self.assign, per_slot)

    def stats(self, present: torch.Tensor) -> dict[str, torch.Tensor]:
        """Monitoring: segments per present edge, mean segment length in steps and (if any) the
        duration latents' mean std. present: [B, E] bool, edges present at some step."""
        w = present.to(torch.float32)
        count = (self.valid.to(torch.float32).sum(-1) * w).sum() / w.sum().clamp_min(1)
        steps = (self.num_steps_per_slot.to(torch.float32).sum(-1) * w).sum() / w.sum().clamp_min(1)
        out = {"segments_per_edge": count, "steps_per_segment": steps / count.clamp_min(1)}
        if self.sigma is not None:
            out["sigma"] = self.sigma
        return out

    def split_at(self, cuts: torch.Tensor, static: bool = False) -> Segmentation:
        """Start a new slot at every ``cuts`` step [B, E, T] bool (where an edge enters, say) that
        falls inside a slot: the slot's steps from the cut on become a slot of their own, whose type
        is read at the cut. The duration latents (``kl``, ``sigma``) stay as drawn, so a cut moves
        no boundary of theirs; the soft gradient of a boundary reaches the piece of its slot on the
        boundary's side. Slots are renumbered in order (S grows by the most cuts any edge has); a
        slot with no step gets start T-1. Segmentations with a slot per step (``assign`` None) or a
        gradient on their boundaries (``weight``) are returned unchanged: they already start a slot
        wherever they need one. ``static``: S grows by T, the most cuts there can be (the extra
        slots hold no step), so the shape does not depend on the cuts and no host synchronisation is
        needed to know it."""
        if self.assign is None or self.weight is not None:
            return self
        t = cuts.shape[-1]
        step = torch.arange(t, device=cuts.device)
        slot = self.assign.detach().argmax(-1)  # [B, E, T]
        # a cut that is not already a slot's first step
        inside = cuts & (self.start.gather(-1, slot) != step)
        shift = inside.long().cumsum(-1)  # [B, E, T]: cuts at or before each step
        extra = t if static else (int(shift[..., -1].max()) if shift.numel() else 0)
        if extra == 0:
            return self
        width = self.assign.shape[-1] + extra
        # step t's old slot j becomes slot j + shift_t: every column of its row moves by shift_t
        column = torch.arange(width, device=cuts.device) - shift.unsqueeze(-1)  # [B, E, T, S']
        padded = torch.nn.functional.pad(self.assign, (0, extra))
        assign = padded.gather(-1, column.clamp_min(0)) * (column >= 0)
        new_slot = slot + shift
        start = torch.full((*slot.shape[:2], width), t - 1, dtype=torch.long, device=cuts.device)
        start = start.scatter_reduce(-1, new_slot, step.expand_as(new_slot), "amin")
        valid = torch.zeros_like(start, dtype=torch.bool).scatter(-1, new_slot, True)
        return Segmentation(start, valid, assign, self.kl, self.sigma, fixed=self.fixed)

    def step_slot(self) -> torch.Tensor:
        """[B, E, T] long: the slot index of every step."""
        if self.assign is None:
            b, e, s = self.start.shape
            return torch.arange(s, device=self.start.device).expand(b, e, s)
        return self.assign.argmax(dim=-1)

