"""Agent pairs whose interaction should look the same all along: the inD consistency check of edge types.

Two kinds of pairs, found per window in raw units (metres, m/s) when the test split is set up:
- ``PARKED``: two vehicles that never move in the window (speed below ``parked_speed`` at every present step);
- ``OPPOSITE``: two moving vehicles heading in opposite directions whose paths in the window never cross.

A model whose edge types mean something should give each such pair one type nearly all the time; the
share of the pair's edge-steps in its dominant type is the check (metric
:class:`dider.evaluation.metrics.PairConsistency`).

Pairs are stored packed, like the windows: ``pair_offsets`` [W+1] (window w owns pairs
pair_offsets[w]:pair_offsets[w+1]), ``pair_agents`` [Q, 2] long (agent positions inside the window) and
``pair_kind`` [Q] long.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from dider.graph import edge_id
from dider.validation import Rule, above, texts, within

OTHER, PARKED, OPPOSITE = 0, 1, 2
CROSSING_CHUNK = 256
KIND_NAMES = {PARKED: "parked", OPPOSITE: "opposite"}


@dataclass(frozen=True)
class PairRules:
    parked_speed: float = 0.5  # m/s: a vehicle whose speed stays below this at every present step is parked
    moving_speed: float = 2.0  # m/s: a vehicle whose mean speed exceeds this is moving
    opposite_cos: float = -0.9  # mean headings with a lower cosine head opposite ways (-0.9: up to ~25 deg off)
    vehicle_classes: tuple[str, ...] = ("car", "truck_bus", "truck", "bus", "van", "trailer", "motorcycle")

    SETTINGS: ClassVar[dict[str, Rule]] = {"parked_speed": above(0), "moving_speed": above(0),
                                           "opposite_cos": within(-1.0, 0.0), "vehicle_classes": texts}

    def __post_init__(self) -> None:
        if not 0 < self.parked_speed <= self.moving_speed:
            raise ValueError(f"data.pairs: need 0 < parked_speed <= moving_speed, got {self.parked_speed}, "
                             f"{self.moving_speed}")
        if not -1 <= self.opposite_cos <= 0:
            raise ValueError(f"data.pairs.opposite_cos={self.opposite_cos}: must lie in [-1, 0]")


def _crossing(a: torch.Tensor, a_ok: torch.Tensor, b: torch.Tensor, b_ok: torch.Tensor) -> torch.Tensor:
    """Do two polylines cross? a, b: [C, T, 2] points, a_ok, b_ok: [C, T] bool (point present; a segment
    needs both of its ends) -> [C] bool. Proper crossings and touching both count."""
    pa, qa = a[:, :-1, None], a[:, 1:, None]  # [C, T-1, 1, 2]
    pb, qb = b[:, None, :-1], b[:, None, 1:]  # [C, 1, T-1, 2]

    def orient(p: torch.Tensor, q: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        return torch.sign((q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1])
                          - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0]))

    # Segments cross when each straddles the other's line (the collinear case needs overlapping boxes).
    o1, o2 = orient(pa, qa, pb), orient(pa, qa, qb)
    o3, o4 = orient(pb, qb, pa), orient(pb, qb, qa)
    straddle = (o1 * o2 <= 0) & (o3 * o4 <= 0)
    collinear = (o1 == 0) & (o2 == 0)
    lo_a, hi_a, lo_b, hi_b = torch.minimum(pa, qa), torch.maximum(pa, qa), torch.minimum(pb, qb), torch.maximum(pb, qb)
    overlap = ((lo_a <= hi_b) & (lo_b <= hi_a)).all(-1)
    hit = straddle & (~collinear | overlap)
    seg_a = (a_ok[:, :-1] & a_ok[:, 1:])[:, :, None]
    seg_b = (b_ok[:, :-1] & b_ok[:, 1:])[:, None, :]
    return (hit & seg_a & seg_b).flatten(1).any(1)


def find_pairs(states: torch.Tensor, mask: torch.Tensor, offsets: torch.Tensor, is_vehicle: torch.Tensor,
               rules: PairRules) -> dict[str, torch.Tensor]:
    """Parked and opposite-direction pairs of every window, vectorised over windows and pairs.

    states: [P, T, 4] raw (x, y, vx, vy) per agent row, mask: [P, T] bool, offsets: [W+1] long (window w
    owns rows offsets[w]:offsets[w+1]), is_vehicle: [P] bool. Returns pair_offsets [W+1], pair_agents [Q, 2]
    (positions inside the window, i < j), pair_kind [Q] (PARKED or OPPOSITE).
    """
    count = offsets[1:] - offsets[:-1]
    speed = states[..., 2:].norm(dim=-1)  # [P, T]
    steps = mask.sum(1).clamp_min(1)
    parked = is_vehicle & ((speed < rules.parked_speed) | ~mask).all(1) & mask.any(1)
    moving = is_vehicle & ((speed * mask).sum(1) / steps > rules.moving_speed)
    heading = (states[..., 2:] * mask[..., None]).sum(1)
    heading = heading / heading.norm(dim=-1, keepdim=True).clamp_min(1e-9)  # [P, 2] mean direction

    # Every unordered pair (i < j) of agents inside each window: the upper triangle of the largest window,
    # kept where both agents exist.
    n_max = max(int(count.max()), 2) if len(count) else 2
    i, j = torch.triu_indices(n_max, n_max, offset=1)
    window = torch.arange(len(count)).repeat_interleave(i.numel())
    i, j = i.repeat(len(count)), j.repeat(len(count))
    exists = j < count[window]
    window, i, j = window[exists], i[exists], j[exists]
    ra, rb = offsets[window] + i, offsets[window] + j
    # Only pairs that can qualify go on (most pairs involve a pedestrian or a slow car): [Q'] from here.
    both_parked = parked[ra] & parked[rb]
    candidate = moving[ra] & moving[rb] & ((heading[ra] * heading[rb]).sum(-1) < rules.opposite_cos)
    keep = both_parked | candidate
    window, i, j, ra, rb = window[keep], i[keep], j[keep], ra[keep], rb[keep]
    together = (mask[ra] & mask[rb]).any(1)  # edges exist only at steps where both are present
    both_parked, candidate = both_parked[keep] & together, candidate[keep] & together
    opposite = candidate.clone()
    # Paths whose bounding boxes are apart cannot cross; the others get the full segment test, in chunks:
    # it holds [C, T-1, T-1] tensors, a few hundred MB at T = 200.
    xy = states[..., :2]
    lo = torch.where(mask[..., None], xy, torch.inf).amin(1)  # [P, 2]
    hi = torch.where(mask[..., None], xy, -torch.inf).amax(1)
    boxes_meet = ((lo[ra] <= hi[rb]) & (lo[rb] <= hi[ra])).all(-1)
    for c in (candidate & boxes_meet).nonzero().squeeze(1).split(CROSSING_CHUNK):
        opposite[c] = ~_crossing(states[ra[c], :, :2], mask[ra[c]], states[rb[c], :, :2], mask[rb[c]])
    kind = torch.where(both_parked, PARKED, torch.where(opposite, OPPOSITE, OTHER))
    keep = kind != OTHER
    pair_offsets = torch.zeros(len(count) + 1, dtype=torch.long)
    pair_offsets[1:] = torch.cumsum(torch.bincount(window[keep], minlength=len(count)), 0)
    return {"pair_offsets": pair_offsets, "pair_agents": torch.stack([i[keep], j[keep]], 1),
            "pair_kind": kind[keep]}


def pair_kind_matrix(pair_offsets: torch.Tensor, pair_agents: torch.Tensor, pair_kind: torch.Tensor,
                     windows: torch.Tensor, n: int) -> torch.Tensor:
    """The kinds of a batch of windows as [B, n(n-1)] long (both directions of a pair share its kind)."""
    lo, hi = pair_offsets[windows], pair_offsets[windows + 1]
    per = hi - lo
    row = torch.repeat_interleave(torch.arange(len(windows)), per)
    q = torch.repeat_interleave(lo - torch.cumsum(per, 0) + per, per) + torch.arange(int(per.sum()))
    a, b = pair_agents[q, 0], pair_agents[q, 1]
    out = torch.zeros(len(windows), n * (n - 1), dtype=torch.long)
    kind = pair_kind[q]
    out[row, edge_id(a, b, n)] = kind
    out[row, edge_id(b, a, n)] = kind
    return out
