"""What each learned edge type means: pair features and per-type statistics against hand-computed values."""

from __future__ import annotations

import pytest
import torch

from dider.evaluation import scoring
from dider.evaluation.type_meaning import (
    PAIR_FEATURES,
    TypeProfile,
    degenerate_types,
    pair_features,
    pair_verdict,
    profile_array,
    profile_notes,
    profile_rows,
    profile_values,
)


def two_agents() -> tuple[torch.Tensor, torch.Tensor]:
    """Agent 0 at (0, 0) moving (1, 0), steady; agent 1 at (3, 4) moving (0, -2), then (0, -1). [1, 2, 2, 4]."""
    states = torch.tensor([[[[0.0, 0, 1, 0], [3, 4, 0, -2]], [[1, 0, 1, 0], [3, 3, 0, -1]]]])
    return states, torch.ones(1, 2, 2, dtype=torch.bool)


def test_pair_features_by_hand() -> None:
    """Edge 0 is 0 -> 1, edge 1 is 1 -> 0. Distance 5 both ways; relative velocity (-1, -2) against the offset
    (3, 4): closing at (3 + 8) / 5 = 2.2; headings (1, 0) and (0, -2) are 90 degrees apart; the receiver's
    velocity changes by |(0, 1)| = 1 on edge 0 (receiver 1) and by 0 on edge 1 (receiver 0)."""
    features, present = pair_features(*two_agents())
    assert features.shape == (1, 2, 1, len(PAIR_FEATURES)) and present.all()
    torch.testing.assert_close(features[0, :, 0].float(), torch.tensor([[5.0, 2.2, 90.0, 1.0], [5.0, 2.2, 90.0, 0.0]]))


def test_an_edge_step_needs_both_agents_and_the_receiver_next() -> None:
    states, mask = two_agents()
    mask[0, 1, 1] = False  # agent 1 gone at frame 1: edge 0 (its receiver) has no next velocity
    assert pair_features(states, mask)[1][0, :, 0].tolist() == [False, True]
    mask[0, 0, 0] = False  # agent 0 absent at frame 0: no pair at all
    assert not pair_features(states, mask)[1].any()


def test_type_profile_with_and_without_by_hand() -> None:
    """Three present edge-steps: type 1 at distances 2 and 4, type 0 at 9; one absent step (distance 100) never
    counts. Type 1: share 2/3, distance 3 while it holds, 9 over the others; type 2 never holds (NaN)."""
    features = torch.zeros(1, 4, 1, len(PAIR_FEATURES))
    features[0, :, 0, 0] = torch.tensor([2.0, 4.0, 9.0, 100.0])
    types = torch.tensor([1, 1, 0, 1]).view(1, 4, 1)
    present = torch.tensor([True, True, True, False]).view(1, 4, 1)
    metric = TypeProfile(3)
    metric.update(types[:, :2], features[:, :2], present[:, :2])  # two batches add up
    metric.update(types[:, 2:], features[:, 2:], present[:, 2:])
    share, with_, without, _ = metric.compute()
    torch.testing.assert_close(share, torch.tensor([1 / 3, 2 / 3, 0.0]))
    torch.testing.assert_close(with_[:2, 0], torch.tensor([9.0, 3.0]))
    torch.testing.assert_close(without[:, 0], torch.tensor([3.0, 9.0, 5.0]))
    assert with_[2].isnan().all()
    values = {k: float(v) for k, v in profile_values("test", metric).items()}
    assert values["test/type1/distance"] == pytest.approx(3.0) and values["test/type1/others/distance"] == 9.0
    rows = profile_rows(values, "test")
    assert [r["type"] for r in rows] == [0, 1, 2] and rows[1]["share"] == pytest.approx(2 / 3)
    assert rows[0]["others_distance"] == pytest.approx(3.0)


def test_a_type_is_about_the_pair_where_it_beats_the_same_type_on_shuffled_pairs() -> None:
    """Two clips of two agents (one pair each way: the shuffled pairs are the other clip's). Clip 0: distances
    1, 5 with types 1, 0; clip 1: distances 6, 2 with types 0, 1;
    closing speed 10 - distance. Type 1 holds on the near pairs: distance 1.5 against 5.5 (gap -4). Read beside
    the other clip's pairs it holds at 6 and 5 (5.5 against 1.5: gap +4). The distances' standard deviation is
    sqrt(16.5 - 3.5^2) = 2.0616, so type 1 is 8 / 2.0616 = 3.88 deviations nearer than on shuffled pairs and as
    much faster closing in; type 0 the opposite."""
    features = torch.zeros(2, 2, 1, len(PAIR_FEATURES))
    features[..., 0, 0] = torch.tensor([[1.0, 5.0], [6.0, 2.0]])
    features[..., 0, 1] = 10 - features[..., 0, 0]
    types = torch.tensor([[1, 0], [0, 1]]).view(2, 2, 1)
    metric = TypeProfile(2)
    metric.update(types, features, torch.ones(2, 2, 1, dtype=torch.bool))
    beyond = metric.compute()[3]
    torch.testing.assert_close(beyond, torch.tensor([[8.0, -8.0], [-8.0, 8.0]]) / 17**0.5 * 2)
    values = {k: float(v) for k, v in profile_values("test", metric).items()}
    assert values["test/type1/beyond_shuffled/distance"] == pytest.approx(-8 / 4.25**0.5, rel=1e-5)
    notes = profile_notes(profile_array(values, "test"))
    assert notes[1].endswith("about the pair: nearer and closing in faster than the same type on shuffled pairs")
    assert notes[0].endswith("about the pair: moving apart faster than the same type on shuffled pairs")
    assert pair_verdict(-0.1, 0.1).startswith("not about") and pair_verdict(float("nan"), 0.0) == ""
    assert pair_verdict(0.0, 0.3) == "about the pair: closing in faster than the same type on shuffled pairs"
    assert pair_verdict(0.0, -0.3) == "about the pair: moving apart faster than the same type on shuffled pairs"


def test_with_three_agents_the_shuffled_pairs_are_the_clips_other_pairs_at_the_same_step() -> None:
    """One clip, three agents, one step; edges 0->1, 0->2, 1->0, 1->2, 2->0, 2->1 at distances 1, 5, 1, 6, 5, 6.
    Type 1 holds on the near pair both ways: 1 against 5.5 (gap -4.5). Read beside the previous edge's pair
    (never its reverse) it holds at 6 and 5 (5.5) against 1, 1, 6, 5 (3.25): gap +2.25. The distances' standard
    deviation is sqrt(124 / 6 - 16) = 2.1602: -6.75 / 2.1602 = -3.125."""
    features = torch.zeros(1, 6, 1, len(PAIR_FEATURES))
    features[0, :, 0, 0] = torch.tensor([1.0, 5.0, 1.0, 6.0, 5.0, 6.0])
    metric = TypeProfile(2)
    metric.update(torch.tensor([1, 0, 1, 0, 0, 0]).view(1, 6, 1), features, torch.ones(1, 6, 1, dtype=torch.bool))
    beyond = metric.compute()[3]
    assert float(beyond[1, 0]) == pytest.approx(-6.75 / (124 / 6 - 16) ** 0.5, rel=1e-5)
    assert beyond[:, 1].isnan().all()  # no closing speed at all: no verdict on it


def test_degenerate_types_are_named_with_their_share() -> None:
    fine = {"test/type0/share": 0.8, "test/type1/share": 0.2}
    assert degenerate_types(fine, "test") is None
    assert degenerate_types({}, "test") is None
    warning = degenerate_types({"test/type0/share": 0.999, "test/type1/share": 0.001, "test/type1/distance": 3.0},
                               "test")
    assert warning is not None and "type 0 on 99.90%, type 1 on 0.10%" in warning and "sparsity" in warning


def test_interaction_rate_counts_the_edge_steps_the_type_table_counts() -> None:
    """Three agents over four frames; agent 2 leaves after frame 1. An edge-step needs both agents at t and the
    receiver at t+1: edges 0 -> 1 and 1 -> 0 hold at steps 0-2, the edges into agent 2 at step 0, the edges out
    of it at steps 0-1 (12 edge-steps). Every posterior type is 1 except edge 0 -> 1 at step 0, and the absent
    edge-steps carry types too (a model does not know they are absent): the rate must be the type table's
    type-1 share, and a run ends at an absence."""
    states = torch.randn(1, 4, 3, 4)
    mask = torch.ones(1, 4, 3, dtype=torch.bool)
    mask[0, 2:, 2] = False
    posterior = torch.ones(1, 6, 3, dtype=torch.long)  # edges [B, E, T-1]
    posterior[0, 0, 0] = 0
    forecast = scoring.Forecast(states[:, 2:], states[:, 2:], mask[:, 2:], posterior, None)
    metrics = scoring.TestMetrics([1], num_types=2)
    metrics.update(batch={"states": states, "mask": mask}, forecast=forecast, posterior=posterior, prior=posterior)
    out = metrics.compute()
    assert out["test/type1/share"].item() == pytest.approx(11 / 12)
    assert out["test/interaction_rate/posterior"].item() == pytest.approx(11 / 12)
    # Runs of 2 (0 -> 1, steps 1-2), 3 (1 -> 0), 1 and 1 (into 2), 2 and 2 (out of 2): 11 steps in 6 runs.
    assert out["test/run_length/posterior"].item() == pytest.approx(11 / 6)
