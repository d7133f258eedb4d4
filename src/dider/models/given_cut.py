"""A given cut of each edge's time axis as a segmentation of held types, scored like the duration
plugin's own (``dider.analysis.diagnose`` reads how the model prices the truth's boundaries).

Shapes: B batch, E edges, T transitions, R LSTM width, K edge types.
"""

from __future__ import annotations

from typing import Any

import torch

from dider.models.hazard import hold_assignment
from dider.models.segments import Segmentation, forced_boundaries


def cut_segmentation(duration: Any, capabilities: Any, h_fwd: torch.Tensor, h_rev: torch.Tensor,
                     cut: torch.Tensor, present: torch.Tensor,
                     step_logits: torch.Tensor | None = None) -> Segmentation:
    """A given cut as a segmentation of held types: cut, present [B, E, T] bool -> slots starting at
    each cut step and at the fixed boundaries (the clip's start, the burn-in's end where the plugin
    has one, entries), with the duration KL of a posterior certain of the cut (the plugin's
    ``cut_kl``; 0 for a plugin without a duration latent). duration: the network's duration plugin;
    capabilities: its :class:`~dider.models.plugins.DurationCapabilities`."""
    b, e, t, _ = h_fwd.shape
    fixed, value = forced_boundaries(t, capabilities.observed, h_fwd.device, present)
    gate = torch.where(fixed, value, cut)
    steps = present.flatten(1).sum(1).clamp_min(1)
    if capabilities.cut_kl and capabilities.held_type and step_logits is not None:
        # each step's segment; its type read at its start
        held = hold_assignment(gate.float()).argmax(-1)
        held = step_logits.argmax(-1).gather(-1, held)
        kl = duration.cut_kl(h_fwd, h_rev, gate, present & ~fixed, steps, held)
    elif capabilities.cut_kl:
        kl = duration.cut_kl(h_fwd, h_rev, gate, present & ~fixed, steps)
    else:
        kl = h_fwd.new_zeros(b, dtype=torch.float32)
    slots = torch.arange(t, device=h_fwd.device).expand(b, e, t)
    return Segmentation(slots, gate, hold_assignment(gate.float().detach()), kl,
                        fixed=fixed.expand(b, e, t))
