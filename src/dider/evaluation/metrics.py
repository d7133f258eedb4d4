"""torchmetrics Metric classes (DDP-safe: every state is a sum)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torchmetrics import Metric


def horizon_list(horizons: Sequence[int]) -> list[int]:
    """The forecast horizons a metric scores, as ints: at least one, each >= 1 (else ValueError)."""
    if not horizons or min(horizons) < 1:
        raise ValueError(f"horizons={list(horizons)}: need at least one horizon, each >= 1")
    return [int(h) for h in horizons]


class HorizonMSE(Metric):
    """MSE at forecast horizons: the h-th predicted step, over present agents and all features.

    update(pred [B, P, N, D], target [B, P, N, D], mask [B, P, N] bool, horizon [B, P, N] long or
    None); compute() -> [len(horizons)], 0-d for a single horizon (torchmetrics squeezes one-element
    results; read it with :func:`dider.evaluation.scoring.horizon_values`). Without ``horizon``
    frame p of the window is horizon p + 1 for every agent (one burn-in for the whole window). With
    it, each element carries its own horizon (e.g. the agent's h-th own predicted step,
    dider.protocol.agent_horizons): horizon h scores, per agent, the present frame whose horizon
    equals h (at most one per agent; <= 0 marks burn-in frames, never scored).
    """

    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(self, horizons: Sequence[int], **kwargs) -> None:
        super().__init__(**kwargs)
        self.horizons = horizon_list(horizons)
        self.add_state("sum_sq", torch.zeros(len(horizons), dtype=torch.float64),
                       dist_reduce_fx="sum")
        self.add_state("count", torch.zeros(len(horizons), dtype=torch.float64),
                       dist_reduce_fx="sum")

    def update(
        self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
        horizon: torch.Tensor | None = None
    ) -> None:
        if max(self.horizons) > pred.shape[1]:
            raise ValueError(f"horizon {max(self.horizons)} exceeds the {pred.shape[1]} predicted "
                             "steps")
        hs = torch.tensor(self.horizons, device=pred.device)
        if horizon is None:
            idx = hs - 1
            # [B, H, N]
            sq = (pred.index_select(1, idx) - target.index_select(1, idx)).pow(2).sum(-1)
            m = mask.index_select(1, idx).to(sq.dtype)
        else:
            # The frame of each (sample, horizon, agent): one gather, so the sums below run in the
            # same layout (and order) as the global case, which they equal when horizon = p + 1
            # everywhere.
            hit = (horizon.unsqueeze(1) == hs.view(1, -1, 1, 1)) & mask.unsqueeze(1)  # [B, H, P, N]
            # [B, H, N]: the (only) matching frame, 0 if none
            frame = hit.to(torch.uint8).argmax(dim=2)
            at = frame.unsqueeze(-1).expand(-1, -1, -1, pred.shape[-1])  # [B, H, N, D]
            sq = (pred.gather(1, at) - target.gather(1, at)).pow(2).sum(-1)  # [B, H, N]
            m = hit.any(dim=2).to(sq.dtype)
        self.sum_sq += (sq * m).sum(dim=(0, 2)).double()
        self.count += (m.sum(dim=(0, 2)) * pred.shape[-1]).double()

    def compute(self) -> torch.Tensor:
        """[H] MSE per horizon; NaN for a horizon no present agent reached (an empty metric is not a
        perfect 0; :func:`dider.evaluation.scoring.horizon_values` warns naming it)."""
        return self.sum_sq / self.count  # float64: squares of large coordinates overflow float32


class HorizonDisplacement(Metric):
    """ADE and FDE of forecast positions (the first two features) at forecast horizons, in the units
    of pred and target: ADE at h is the mean Euclidean distance over the present predicted frames of
    horizons 1..h, FDE at h over those of horizon h.

    update(pred [B, P, N, D], target [B, P, N, D], mask [B, P, N] bool, horizon [B, P, N] long or
    None), with horizons read as in :class:`HorizonMSE` (frame p is horizon p + 1 without
    ``horizon``); compute() -> [2, H] (ADE, FDE), NaN at a horizon that no present agent reached (an
    empty metric is not a perfect 0).
    """

    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(self, horizons: Sequence[int], **kwargs) -> None:
        super().__init__(**kwargs)
        self.horizons = horizon_list(horizons)
        self.add_state("sums", torch.zeros(2, len(horizons), dtype=torch.float64),
                       dist_reduce_fx="sum")
        self.add_state("counts", torch.zeros(2, len(horizons), dtype=torch.float64),
                       dist_reduce_fx="sum")

    def update(
        self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
        horizon: torch.Tensor | None = None
    ) -> None:
        if max(self.horizons) > pred.shape[1]:
            raise ValueError(f"horizon {max(self.horizons)} exceeds the {pred.shape[1]} predicted "
                             "steps")
        if horizon is None:
            horizon = (torch.arange(1, mask.shape[1] + 1, device=mask.device).view(1, -1, 1)
                       .expand_as(mask))
        dist = (pred[..., :2].double() - target[..., :2].double()).norm(dim=-1)  # [B, P, N]
        hs = torch.tensor(self.horizons, device=pred.device).view(-1, 1, 1, 1)
        # burn-in frames (horizon <= 0) are never scored
        scored = (mask & (horizon >= 1)).unsqueeze(0)
        # [H, B, P, N]
        upto, at = scored & (horizon.unsqueeze(0) <= hs), scored & (horizon.unsqueeze(0) == hs)
        both = torch.stack([upto, at])  # [2, H, B, P, N]
        # a masked NaN (absent agent) never counts
        self.sums += torch.where(both, dist, 0.0).sum(dim=(2, 3, 4))
        self.counts += both.sum(dim=(2, 3, 4)).double()

    def compute(self) -> torch.Tensor:
        """[2, H]: ADE and FDE per horizon."""
        return self.sums / self.counts  # float64; 0 / 0 = NaN for an empty horizon


class EdgeAccuracy(Metric):
    """Recall per ground-truth class: "no interaction" (type 0) and "interaction" (any type > 0).

    Type 0 is pinned to "no interaction", so no permutation search is needed; with more than two
    learned types an interacting edge counts as found when any interaction type (> 0) is predicted.
    update(pred [..], target [..] long, mask [..] bool or None); compute() -> [2] (none,
    interaction).
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.add_state("correct", torch.zeros(2, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("total", torch.zeros(2, dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, pred: torch.Tensor, target: torch.Tensor,
               mask: torch.Tensor | None = None) -> None:
        truth, found = (target > 0).long(), (pred > 0).long()
        keep = torch.ones_like(truth, dtype=torch.bool) if mask is None else mask
        hit = (truth == found) & keep
        self.correct += torch.bincount(truth[hit], minlength=2).double()
        self.total += torch.bincount(truth[keep], minlength=2).double()

    def compute(self) -> torch.Tensor:
        """[2] recall of (none, interaction); NaN for a class with no edge-step."""
        return (self.correct / self.total).float()


def switches(types: torch.Tensor) -> torch.Tensor:
    """[..., T] types -> [..., T-1] bool: the type changes between step t and t+1 (a switch at
    t+1)."""
    return types[..., 1:] != types[..., :-1]


class SegmentStats(Metric):
    """Readability of inferred interactions: segments per edge and type switches per 100 steps.

    update(types [B, E, T] long, edge_mask [B, E] bool or None); compute() -> [segments_per_edge,
    switches_per_100].
    """

    is_differentiable = False
    full_state_update = False

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        for name in ("switches", "edges", "steps"):
            self.add_state(name, torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, types: torch.Tensor, edge_mask: torch.Tensor | None = None) -> None:
        sw = switches(types).sum(-1).double()  # [B, E]
        keep = torch.ones_like(sw, dtype=torch.bool) if edge_mask is None else edge_mask
        self.switches += sw[keep].sum()
        self.edges += keep.sum()
        self.steps += keep.sum() * types.shape[-1]

    def compute(self) -> torch.Tensor:
        per_edge = 1 + self.switches / self.edges.clamp_min(1)
        per_100 = 100 * self.switches / self.steps.clamp_min(1)
        return torch.stack([per_edge, per_100]).float()


class InteractionRunLength(Metric):
    """How long and how often edges interact: the mean length, in steps, of a run of one interaction
    type (any type but 0, "none"), and the share of edge-steps with an interaction. Against the
    ground truth's, the first shows whether inferred interactions end too early or run on, the
    second whether a model marks interactions as often as the data have them (a sparsity prior asks
    for its own rate, e.g. DNRI's 10%).

    update(types [B, E, T] long, present [B, E, T] or [B, E] bool or None: the edge-steps, or the
    whole edges, that count; elsewhere a step is absent, as a type of -1 is, and an absence ends a
    run); compute() -> [run length, rate] (the run length NaN without any run).
    """

    is_differentiable = False
    full_state_update = False

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        for name in ("steps", "runs", "total"):
            self.add_state(name, torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, types: torch.Tensor, present: torch.Tensor | None = None) -> None:
        if present is not None:
            types = types.masked_fill(
                ~(present if present.dim() == types.dim() else present.unsqueeze(-1)), -1)
        active = types > 0  # [B, E, T]
        starts = active.clone()
        starts[..., 1:] &= switches(types)  # a run starts at t = 0 or where the type changes
        self.steps += active.sum()
        self.runs += starts.sum()
        self.total += (types >= 0).sum()  # -1: an absent edge-step

    def compute(self) -> torch.Tensor:
        length = (self.steps / self.runs if self.runs > 0
                  else torch.full_like(self.steps, float("nan")))
        return torch.stack([length, self.steps / self.total.clamp_min(1)]).float()


class BoundaryF1(Metric):
    """F1 of inferred switch times against ground-truth switch times, matched within +-``tolerance``
    steps.

    A predicted switch is correct when a true switch lies within the tolerance, and a true switch is
    found when a predicted one does (micro-averaged over all edges and clips). update(pred [B, E, T]
    long, target [B, E, T] long); compute() -> scalar F1 (1 when neither has switches).
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False

    def __init__(self, tolerance: int = 2, **kwargs) -> None:
        super().__init__(**kwargs)
        self.tolerance = tolerance
        for name in ("pred_hit", "pred_all", "true_hit", "true_all"):
            self.add_state(name, torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")

    def _near(self, events: torch.Tensor) -> torch.Tensor:
        """Dilate boolean events [..., T] by the tolerance along time."""
        if events.numel() == 0:  # a one-step window has no transitions, so no switches
            return events
        k = 2 * self.tolerance + 1
        flat = events.reshape(-1, 1, events.shape[-1]).float()
        return (torch.nn.functional.max_pool1d(flat, k, stride=1, padding=self.tolerance)
                .view(events.shape) > 0)

    def update(self, pred: torch.Tensor, target: torch.Tensor) -> None:
        # Switches of the raw types on both sides: a change 1 -> 2 of the truth is a switch too.
        self.update_events(switches(pred), switches(target))

    def update_events(self, p: torch.Tensor, g: torch.Tensor) -> None:
        """Predicted and true events [..., T] bool, matched within the tolerance along the last
        axis."""
        self.pred_hit += (p & self._near(g)).sum().double()
        self.true_hit += (g & self._near(p)).sum().double()
        self.pred_all += p.sum().double()
        self.true_all += g.sum().double()

    def compute(self) -> torch.Tensor:
        if self.pred_all == 0 and self.true_all == 0:
            return torch.ones((), device=self.pred_all.device)
        precision = self.pred_hit / self.pred_all.clamp_min(1)
        recall = self.true_hit / self.true_all.clamp_min(1)
        return (2 * precision * recall / (precision + recall).clamp_min(1e-12)).float()


class OwnCut(BoundaryF1):
    """Where a duration plugin's own segments start, against the types they hold and the true
    switches.

    Only the boundaries a plugin chooses count: not the clip's first step, the burn-in's end or an
    edge's entry (``free`` false there). ``on_switch``: the share of own boundaries where the held
    type changes (a boundary whose new segment reads the type held before it cuts nothing readable);
    ``boundary_f1``: own boundaries against the true type switches at the free steps, within
    +-``tolerance`` steps (unmerged: every own boundary counts, also one between two segments of the
    same type); ``per_constant_edge``: own boundaries per edge whose true type never switches at its
    free steps (the truth has none there).

    update(slot [B, E, T] long (each step's slot), held [B, E, T] long (the type held at each step),
    free [B, E, T] bool (steps where the plugin may start a segment), truth [B, E, T] long or None);
    compute() -> [on_switch, boundary_f1, per_constant_edge] (on_switch NaN without an own boundary;
    the others NaN without truth).
    """

    def __init__(self, tolerance: int = 2, **kwargs) -> None:
        super().__init__(tolerance, **kwargs)
        for name in ("own", "own_on_switch", "with_truth", "constant_own", "constant_edges"):
            self.add_state(name, torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, slot: torch.Tensor, held: torch.Tensor,  # type: ignore[override]
               free: torch.Tensor, truth: torch.Tensor | None = None) -> None:
        own = switches(slot) & free[..., 1:]  # [B, E, T-1]: a new slot at step t >= 1
        self.own += own.sum().double()
        self.own_on_switch += (own & switches(held)).sum().double()
        if truth is not None:
            self.with_truth += 1
            true = switches(truth) & free[..., 1:]
            self.update_events(own, true)
            # [B, E]: free steps, and no true switch at them
            constant = free[..., 1:].any(-1) & ~true.any(-1)
            self.constant_own += (own.sum(-1) * constant).sum().double()
            self.constant_edges += constant.sum().double()

    def compute(self) -> torch.Tensor:
        nan = torch.full_like(self.own, float("nan"))  # on the metric's device, as the states
        share = self.own_on_switch / self.own if self.own > 0 else nan
        f1 = super().compute() if self.with_truth > 0 else nan
        constant = self.constant_own / self.constant_edges if self.constant_edges > 0 else nan
        return torch.stack([share.float(), f1.float(), constant.float()])


class PairConsistency(Metric):
    """The inD consistency check: for each kind of pair (parked, opposite-direction non-crossing;
    see :mod:`dider.data.pairs`), the share of its edge-steps that fall in its most frequent edge
    type, and that type.

    update(types [B, E, T] long, pair_kind [B, E] long (0: not checked), present [B, E, T] bool);
    compute() -> (share [kinds], dominant type [kinds], edge-steps [kinds]); share is NaN for a kind
    never seen.
    """

    is_differentiable = False
    full_state_update = False

    def __init__(self, num_types: int, num_kinds: int = 2, **kwargs) -> None:
        super().__init__(**kwargs)
        self.num_types, self.num_kinds = num_types, num_kinds
        self.add_state("counts", torch.zeros(num_kinds, num_types, dtype=torch.float64),
                       dist_reduce_fx="sum")

    def update(self, types: torch.Tensor, pair_kind: torch.Tensor, present: torch.Tensor) -> None:
        kind = pair_kind.unsqueeze(-1).expand_as(types)
        keep = present & (kind > 0)
        cell = (kind[keep] - 1) * self.num_types + types[keep]
        self.counts += (torch.bincount(cell, minlength=self.num_kinds * self.num_types)
                        .view_as(self.counts).double())

    def compute(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        total = self.counts.sum(1)
        top, dominant = self.counts.max(1)
        share = torch.where(total > 0, top / total.clamp_min(1),
                            torch.full_like(total, float("nan")))
        return share.float(), dominant, total
