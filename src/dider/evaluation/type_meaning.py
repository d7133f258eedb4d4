"""What each learned edge type means: statistics of the pairs while they hold it, beside the pairs
that do not.

A learned type is a label the model invented; these statistics, in the data's units, say what it
tracks: how often it holds, how far apart its pairs are, whether they close in, how aligned they
move, how hard the receiver changes its velocity. A type that holds on almost no edge-step, or on
almost all, explains nothing (:func:`degenerate_types`).

Shapes: B clips, T frames, N agents, E = N(N-1) edges, K edge types, F pair features.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import torch
from torchmetrics import Metric

from dider.graph import edge_index, edge_mask

# Per edge-step (sender -> receiver, transition t -> t+1), in the data's units: the distance, the
# closing speed (> 0: approaching), the angle between the two velocities (degrees, 0: same heading),
# the change of the receiver's velocity over the step (velocity units per step).
PAIR_FEATURES = ("distance", "closing_speed", "relative_heading_deg", "receiver_accel")
# A type on fewer, or more, of the present edge-steps than this share is degenerate.
DEGENERATE_SHARE = 0.005


def pair_features(states: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """states [B, T, N, >=4] (positions, velocities, data units), mask [B, T, N] bool -> features
    [B, E, T-1, F] (:data:`PAIR_FEATURES`) and present [B, E, T-1] bool (both agents at t, the
    receiver at t+1)."""
    send, recv = edge_index(states.shape[2], states.device)
    # float32: [B, T-1, E, 2] intermediates of large scenes (inD: E ~ 3500) stay affordable.
    # Positions and velocities are scaled by powers of two (exact) to at most 1 first, so that
    # squares of coordinates of any size stay in float32's range; the features are scaled back in
    # float64.
    # [2]: positions, velocities
    scale = states[..., :4].abs().amax(dim=(0, 1, 2)).view(2, 2).amax(1).double()
    scale = torch.exp2(torch.ceil(torch.log2(scale.clamp_min(1.0))))
    x = (states[..., :4].double() / scale.repeat_interleave(2)).float()
    pos, vel = x[:, :-1, :, :2], x[:, :-1, :, 2:4]  # [B, T-1, N, 2]
    # [B, T-1, E, 2]
    rel, rel_vel = pos[:, :, recv] - pos[:, :, send], vel[:, :, recv] - vel[:, :, send]
    distance = rel.norm(dim=-1)
    closing = -(rel * rel_vel).sum(-1) / distance.clamp_min(1e-9)
    v_s, v_r = vel[:, :, send], vel[:, :, recv]
    cross = v_s[..., 0] * v_r[..., 1] - v_s[..., 1] * v_r[..., 0]
    heading = torch.rad2deg(torch.atan2(cross, (v_s * v_r).sum(-1)).abs())
    accel = (x[:, 1:, recv, 2:4] - v_r).norm(dim=-1)
    # distance, closing, heading, accel
    unit = torch.stack([scale[0], scale[1], scale.new_ones(()), scale[1]])
    features = ((torch.stack([distance, closing, heading, accel], dim=-1).double() * unit)
                .transpose(1, 2))
    present = (edge_mask(mask[:, :-1]) & mask[:, 1:, recv]).transpose(1, 2)
    return features, present


# The features whose association with a type says the type is about the pair, and the smallest
# effect (in the feature's standard deviation over all present edge-steps) beyond that on shuffled
# pairs that counts: a small effect in Cohen's terms.
PAIR_SPECIFIC = ("distance", "closing_speed")
PAIR_EFFECT = 0.2


class TypeProfile(Metric):
    """Per edge type: its share of the present edge-steps and the mean of each pair feature while it
    holds, and over the other present edge-steps; and the same type on shuffled pairs (each edge's
    types read beside another pair of the same clip at the same step: the previous edge, never the
    reverse pair; with two agents, the previous clip's), whose with-minus-others gap in distance and
    closing speed is what a type shows that follows the scene and the time rather than the pair.

    update(types [B, E, T-1] long, features [B, E, T-1, F], present [B, E, T-1] bool); compute() ->
    share [K], mean_with [K, F], mean_without [K, F] (NaN where no edge-step is counted),
    beyond_shuffled [K, 2]: the gap (with - others) in :data:`PAIR_SPECIFIC` minus the shuffled
    pairs' gap, over the feature's standard deviation.
    """

    is_differentiable = False
    full_state_update = False

    def __init__(self, num_types: int, **kwargs) -> None:
        super().__init__(**kwargs)
        self.num_types = num_types
        f = len(PAIR_FEATURES)
        for name, shape in (("sums", (num_types, f)), ("counts", (num_types,)), ("squares", (f,)),
                            ("shuffled_sums", (num_types, f)), ("shuffled_counts", (num_types,)),
                            ("shuffled_total", (f,)), ("shuffled_steps", ())):
            self.add_state(name, torch.zeros(shape, dtype=torch.float64), dist_reduce_fx="sum")

    def _weights(self, types: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        onehot = torch.nn.functional.one_hot(types.clamp(0, self.num_types - 1), self.num_types)
        return (onehot * present.unsqueeze(-1)).double()  # [B, E, T-1, K]

    def update(self, types: torch.Tensor, features: torch.Tensor, present: torch.Tensor) -> None:
        values = features.double().nan_to_num()
        weight = self._weights(types, present)
        self.sums += torch.einsum("betk,betf->kf", weight, values)
        self.counts += weight.sum(dim=(0, 1, 2))
        self.squares += (values.square() * present.unsqueeze(-1)).sum(dim=(0, 1, 2))
        # another pair of the same clip at the same step (of another clip with two agents, whose
        # two edges are one pair)
        dim = 1 if types.shape[1] > 2 else 0
        if types.shape[dim] < 2:
            return
        other, there = values.roll(1, dim), present.roll(1, dim)
        both = present & there
        weight = self._weights(types, both)
        self.shuffled_sums += torch.einsum("betk,betf->kf", weight, other)
        self.shuffled_counts += weight.sum(dim=(0, 1, 2))
        self.shuffled_total += (other * both.unsqueeze(-1)).sum(dim=(0, 1, 2))
        self.shuffled_steps += both.sum()

    def compute(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        total, total_sums = self.counts.sum(), self.sums.sum(0)
        share = self.counts / total
        mean_with = self.sums / self.counts[:, None]
        mean_without = (total_sums - self.sums) / (total - self.counts)[:, None]
        shuffled_with = self.shuffled_sums / self.shuffled_counts[:, None]
        shuffled_without = (self.shuffled_total - self.shuffled_sums) / (self.shuffled_steps
                                                                         - self.shuffled_counts)[
                                                                             :, None]
        std = (self.squares / total - (total_sums / total).square()).clamp_min(0).sqrt()
        gap = (mean_with - mean_without) - (shuffled_with - shuffled_without)
        cols = [PAIR_FEATURES.index(name) for name in PAIR_SPECIFIC]
        beyond = gap[:, cols] / std[cols]
        return share.float(), mean_with.float(), mean_without.float(), beyond.float()


def profile_values(prefix: str, metric: TypeProfile) -> dict[str, torch.Tensor]:
    """``prefix/typeK/share`` and, per feature, ``prefix/typeK/FEATURE`` (while K holds) and
    ``prefix/typeK/others/FEATURE`` (the other present edge-steps);
    ``prefix/typeK/beyond_shuffled/FEATURE`` for :data:`PAIR_SPECIFIC` (:class:`TypeProfile`)."""
    share, mean_with, mean_without, beyond = metric.compute()
    out: dict[str, torch.Tensor] = {}
    for k in range(metric.num_types):
        out[f"{prefix}/type{k}/share"] = share[k]
        for f, name in enumerate(PAIR_FEATURES):
            out[f"{prefix}/type{k}/{name}"] = mean_with[k, f]
            out[f"{prefix}/type{k}/others/{name}"] = mean_without[k, f]
        for f, name in enumerate(PAIR_SPECIFIC):
            out[f"{prefix}/type{k}/beyond_shuffled/{name}"] = beyond[k, f]
    return out


def pair_verdict(beyond_distance: float, beyond_closing: float) -> str:
    """A type's bearing on the pair, from its gaps beyond shuffled pairs (:class:`TypeProfile`)."""
    if not (math.isfinite(beyond_distance) and math.isfinite(beyond_closing)):
        return ""
    found = [what for what, yes in (("nearer", beyond_distance <= -PAIR_EFFECT),
                                    ("closing in faster", beyond_closing >= PAIR_EFFECT),
                                    ("moving apart faster", beyond_closing <= -PAIR_EFFECT)) if yes]
    if found:
        return f"about the pair: {' and '.join(found)} than the same type on shuffled pairs"
    return ("not about the pair: no nearer, and closing in or moving apart no faster, than the "
            "same type on shuffled pairs (a state of the agents' own motion?)")


def profile_rows(values: dict[str, float], prefix: str) -> list[dict[str, float]]:
    """The values of :func:`profile_values` as one row per type: type, share, each feature,
    others_FEATURE."""
    rows, k = [], 0
    while f"{prefix}/type{k}/share" in values:
        row = {"type": k, "share": values[f"{prefix}/type{k}/share"]}
        for name in PAIR_FEATURES:
            row[name] = values[f"{prefix}/type{k}/{name}"]
            row[f"others_{name}"] = values[f"{prefix}/type{k}/others/{name}"]
        for name in PAIR_SPECIFIC:
            row[f"beyond_shuffled_{name}"] = values.get(f"{prefix}/type{k}/beyond_shuffled/{name}",
                                                        math.nan)
        rows.append(row)
        k += 1
    return rows


def degenerate_types(values: dict[str, float], prefix: str) -> str | None:
    """A warning naming each type whose share of the present edge-steps is below
    :data:`DEGENERATE_SHARE` or above 1 - it, with what to try; None when every type is in between
    (or there is no profile)."""
    shares = {int(k.split("/type")[1].split("/")[0]): v for k, v in values.items()
              if k.startswith(f"{prefix}/type") and k.endswith("/share")}
    odd = [(k, s) for k, s in sorted(shares.items())
           if math.isfinite(s) and not DEGENERATE_SHARE <= s <= 1 - DEGENERATE_SHARE]
    if not odd:
        return None
    named = ", ".join(f"type {k} on {100 * s:.2f}%" for k, s in odd)
    return (f"degenerate edges: {named} of the present edge-steps, so the types tell the pairs "
            "apart nowhere. Try a weaker sparsity term (model.net.objective.sparsity.weight, "
            ".no_edge_prob), more epochs, or check that the pairs interact within a clip at "
            "data.source.frame_rate (windows long enough to see a reaction)")


def profile_array(values: Mapping[str, float], prefix: str) -> np.ndarray | None:
    """The profile as [K, 1 + 2F + 2] float64 (share, the features while the type holds, over the
    others, the gaps beyond shuffled pairs), as the explorer's legend reads it from ``clips.npz``
    (``type_profile``); None without a profile."""
    rows = profile_rows(dict(values), prefix)
    if not rows:
        return None
    keys = ["share", *PAIR_FEATURES, *(f"others_{f}" for f in PAIR_FEATURES),
            *(f"beyond_shuffled_{f}" for f in PAIR_SPECIFIC)]
    return np.array([[row[k] for k in keys] for row in rows], dtype=np.float64)


def profile_notes(profile: np.ndarray) -> list[str]:
    """One line per type from :func:`profile_array`: its share and each feature beside the
    others'."""
    f = len(PAIR_FEATURES)
    labels = ("distance", "closing speed", "heading apart", "receiver accel")
    notes = []
    for row in profile:
        parts = [f"{100 * row[0]:.1f}% of edge-steps"]
        parts += [f"{label} {row[1 + i]:.3g} (others {row[1 + f + i]:.3g})"
                  for i, label in enumerate(labels)]
        if len(row) > 1 + 2 * f and (verdict := pair_verdict(row[1 + 2 * f], row[2 + 2 * f])):
            parts.append(verdict)  # profiles written before the shuffled pairs have no such columns
        notes.append(" \u00b7 ".join(parts))
    return notes
