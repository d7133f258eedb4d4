"""Windows stored packed: one row per agent per window, window w owning rows offsets[w]:offsets[w+1] (windows have
different agent counts). A cut (:class:`~dider.data.tracks.Tracks`) is a dict of per-row tensors (``ROW_KEYS``),
per-window tensors (``WINDOW_KEYS``), ``offsets`` [W+1] long and ``class_names``; these join the scenes' windows and
select some of them."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

from dider.data.common import ragged_rows

ROW_KEYS = ("states", "mask", "agent", "agent_class")  # [P, ...]; agent_class may be None
WINDOW_KEYS = ("start", "scene", "frame", "clip")  # [W] long; clip only once numbered


def join(parts: Sequence[dict[str, Any]], seq_len: int) -> dict[str, Any]:
    """The windows of several parts (scenes, recordings; each a cut) in order, as one cut: states [P, T, 4], mask
    [P, T], agent and agent_class [P], offsets [W+1] (shifted), start, scene, frame [W]; class codes remapped to the
    sorted union of the parts' class names (None where the parts have no classes). No part: no window of ``seq_len``
    steps."""
    if not parts:
        return {"states": torch.zeros(0, seq_len, 4), "mask": torch.zeros(0, seq_len, dtype=torch.bool),
                "offsets": torch.zeros(1, dtype=torch.long), "agent": torch.zeros(0, dtype=torch.long),
                "agent_class": None, "class_names": None,
                **{k: torch.zeros(0, dtype=torch.long) for k in WINDOW_KEYS if k != "clip"}}
    shifts = torch.tensor([0, *(int(p["offsets"][-1]) for p in parts)]).cumsum(0)
    out = {k: torch.cat([p[k] for p in parts]) for k in ("states", "mask", "agent", "start", "scene", "frame")}
    out["offsets"] = torch.cat([torch.zeros(1, dtype=torch.long),
                                *(p["offsets"][1:] + shift for p, shift in zip(parts, shifts[:-1], strict=True))])
    if parts[0]["class_names"] is None:
        out["agent_class"] = out["class_names"] = None
        return out
    names = sorted(set().union(*(p["class_names"] for p in parts)))
    lut = [torch.tensor([names.index(c) for c in p["class_names"]] or [0], dtype=torch.long) for p in parts]
    out["agent_class"] = torch.cat([m[p["agent_class"]] for m, p in zip(lut, parts, strict=True)])
    out["class_names"] = names
    return out


def select_windows(cut: dict[str, Any], idx: torch.Tensor) -> dict[str, Any]:
    """The windows ``idx`` [K] long of a cut, in that order (the cut itself when ``idx`` keeps every window in
    order)."""
    if len(idx) == len(cut["frame"]) and bool((idx == torch.arange(len(idx))).all()):
        return cut
    rows, offsets = ragged_rows(cut["offsets"], idx)
    out = dict(cut, offsets=offsets)
    out.update({k: cut[k][idx] for k in WINDOW_KEYS if k in cut})
    out.update({k: None if cut[k] is None else cut[k][rows] for k in ROW_KEYS})
    return out
