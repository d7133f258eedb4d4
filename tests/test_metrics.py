"""The torchmetrics classes of dider.evaluation.metrics against values worked out by hand.

Each metric gets: a small example with its expected value derived in a comment, masked-out entries that
must not count, its documented value with no data, and a DDP-style merge (two instances fed one half each,
merged, equal one fed the whole). Inputs are fixed tensors, never random, so every expected value is exact.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence

import pytest
import torch
from torchmetrics import Metric
from torchmetrics.utilities.data import dim_zero_sum

from dider.evaluation.metrics import (
    BoundaryF1,
    EdgeAccuracy,
    HorizonDisplacement,
    HorizonMSE,
    InteractionRunLength,
    OwnCut,
    PairConsistency,
    SegmentStats,
)
from dider.evaluation.scoring import cv_verdict, displacement_values, leading_first

L = torch.long


def assert_values(actual: torch.Tensor, expected: float | Sequence[float]) -> None:
    """compute() divides float64 sums (the error metrics keep float64; the shares cast to float32): compare in the
    metric's dtype."""
    torch.testing.assert_close(actual, torch.tensor(expected, dtype=actual.dtype))


def compute_quietly(metric: Metric) -> torch.Tensor | tuple[torch.Tensor, ...]:
    """compute() on a metric that never saw update(): torchmetrics warns about that, which is the point here."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*was called before the ``update`` method.*")
        return metric.compute()


def merged(make: Callable[[], Metric], first: Sequence[tuple], second: Sequence[tuple]) -> Metric:
    """What DDP does: one metric per rank, each updated with its share, then the states reduced."""
    a, b = make(), make()
    for args in first:
        a.update(*args)
    for args in second:
        b.update(*args)
    a.merge_state(b)
    return a


def whole(make: Callable[[], Metric], *updates: tuple) -> Metric:
    metric = make()
    for args in updates:
        metric.update(*args)
    return metric


def assert_same_states(a: Metric, b: Metric) -> None:
    for name in a._defaults:
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=0)


@pytest.mark.parametrize("make", [
    lambda: HorizonMSE([1, 2]), EdgeAccuracy, SegmentStats, BoundaryF1, lambda: PairConsistency(3),
    lambda: HorizonDisplacement([1, 2]),
    InteractionRunLength, OwnCut,
], ids=["HorizonMSE", "EdgeAccuracy", "SegmentStats", "BoundaryF1", "PairConsistency", "HorizonDisplacement",
        "InteractionRunLength", "OwnCut"])
def test_every_state_is_a_sum(make: Callable[[], Metric]) -> None:
    """The module promises DDP safety by summing every state: what makes merge_state (and the all-reduce)
    exact, and what the by-hand merges below rely on."""
    metric = make()
    assert metric._defaults
    assert all(metric._reductions[name] is dim_zero_sum for name in metric._defaults)
    assert metric.full_state_update is False


# ---------------------------------------------------------------------------------------------- HorizonMSE
# One sample, P=3 frames, N=2 agents, D=2 features, target 0. The squared error summed over features is a
# distinct power of two per (frame, agent), so any wrongly included entry changes the value visibly:
#            agent 0         agent 1
# frame 0:  [1,0] -> 1      [1,1] -> 2
# frame 1:  [2,0] -> 4      [2,2] -> 8
# frame 2:  [4,0] -> 16     [4,4] -> 32
PRED = torch.tensor([[[1.0, 0.0], [1.0, 1.0]], [[2.0, 0.0], [2.0, 2.0]], [[4.0, 0.0], [4.0, 4.0]]]).unsqueeze(0)
TARGET = torch.zeros_like(PRED)
ALL = torch.ones(1, 3, 2, dtype=torch.bool)


def test_horizon_mse_global_horizons() -> None:
    """No ``horizon``: frame p is horizon p + 1; the mean is over present agents AND features (count x D)."""
    m = HorizonMSE([1, 3])
    m.update(PRED, TARGET, ALL)
    # h1 = frame 0: (1 + 2) / (2 agents * 2 features) = 0.75; h3 = frame 2: (16 + 32) / 4 = 12.
    # Frame 1 (4, 8) is no requested horizon and must not leak in.
    assert_values(m.compute(), [0.75, 12.0])


def test_horizon_mse_global_mask() -> None:
    """An absent agent drops out of both the sum and the count, even with a huge error."""
    pred = PRED.clone()
    pred[0, 2, 1] = 1e3  # agent 1 at frame 2: absent below, so this must not count
    mask = ALL.clone()
    mask[0, 2, 1] = False
    m = HorizonMSE([1, 3])
    m.update(pred, TARGET, mask)
    # h1 unchanged 0.75; h3 = 16 / (1 agent * 2 features) = 8.
    assert_values(m.compute(), [0.75, 8.0])


def test_horizon_mse_per_agent_horizons() -> None:
    """With ``horizon``: agent 0 has no burn-in (horizons 1, 2, 3), agent 1 one burn-in frame (0, 1, 2)."""
    horizon = torch.tensor([[[1, 0], [2, 1], [3, 2]]])  # [B, P, N]
    m = HorizonMSE([1, 2, 3])
    m.update(PRED, TARGET, ALL, horizon)
    # h1: agent 0 frame 0 (1) + agent 1 frame 1 (8) -> 9 / 4 = 2.25
    # h2: agent 0 frame 1 (4) + agent 1 frame 2 (32) -> 36 / 4 = 9
    # h3: agent 0 frame 2 (16) only; agent 1 never reaches horizon 3 -> 16 / 2 = 8
    # agent 1's burn-in frame 0 (2) is never scored.
    assert_values(m.compute(), [2.25, 9.0, 8.0])


def test_horizon_mse_per_agent_mask() -> None:
    """A frame at the right horizon but absent is not scored (and no other frame of that agent stands in)."""
    horizon = torch.tensor([[[1, 0], [2, 1], [3, 2]]])
    mask = ALL.clone()
    mask[0, 1, 1] = False  # agent 1's horizon-1 frame
    pred = PRED.clone()
    pred[0, 1, 1] = 1e3
    m = HorizonMSE([1, 2])
    m.update(pred, TARGET, mask, horizon)
    # h1: agent 0 frame 0 only -> 1 / 2 = 0.5; h2 unchanged -> (4 + 32) / 4 = 9
    assert_values(m.compute(), [0.5, 9.0])


def test_horizon_mse_per_agent_equals_global_when_horizon_is_frame_plus_one() -> None:
    """horizon = p + 1 everywhere is the global case; the states match to the bit."""
    mask = torch.tensor([[[True, True], [False, True], [True, False]]])
    horizon = torch.arange(1, 4).view(1, 3, 1).expand(1, 3, 2)
    a, b = HorizonMSE([1, 2, 3]), HorizonMSE([1, 2, 3])
    a.update(PRED, TARGET, mask)
    b.update(PRED, TARGET, mask, horizon)
    assert_same_states(a, b)
    # (1 + 2) / 4, 8 / 2, 16 / 2
    assert_values(b.compute(), [0.75, 4.0, 8.0])


def test_horizon_mse_empty_is_nan() -> None:
    """No data (no update, all masked, or a horizon no agent reaches) is NaN, never a perfect 0."""
    assert compute_quietly(HorizonMSE([1, 2])).isnan().all()

    m = HorizonMSE([1, 3])
    m.update(PRED, TARGET, torch.zeros_like(ALL))
    assert m.count.tolist() == [0.0, 0.0]
    assert m.compute().isnan().all()

    m = HorizonMSE([1, 3])
    m.update(PRED, TARGET, ALL, torch.tensor([[[0, 0], [0, 1], [0, 2]]]))  # only agent 1 leaves burn-in, late
    # h1: agent 1 frame 1 (8) -> 8 / 2 = 4; h3: nobody -> NaN
    assert m.compute()[0].item() == 4.0 and m.compute()[1].isnan()


def test_horizon_mse_single_horizon_keeps_its_dimension() -> None:
    """protocol.horizons=[h] passes config validation; val/test logging reads the values with horizon_values
    (torchmetrics squeezes a one-element compute() to 0-d)."""
    from dider.evaluation.scoring import horizon_values

    m = HorizonMSE([3])
    m.update(PRED, TARGET, ALL)
    # h3 = frame 2: (16 + 32) / 4 = 12
    assert_values(m.compute().reshape(-1), [12.0])
    assert horizon_values("val/mse", m) == {"val/mse/h03": torch.tensor(12.0)}


def test_horizon_mse_rejects_bad_horizons() -> None:
    with pytest.raises(ValueError, match="at least one horizon"):
        HorizonMSE([])
    with pytest.raises(ValueError, match="at least one horizon"):
        HorizonMSE([0, 1])
    with pytest.raises(ValueError, match="exceeds the 3 predicted steps"):
        HorizonMSE([4]).update(PRED, TARGET, ALL)


@pytest.mark.parametrize("per_agent", [False, True])
def test_horizon_mse_merge(per_agent: bool) -> None:
    """Two samples split across two 'ranks' merge into the single-rank result."""
    pred = torch.cat([PRED, 2 * PRED])
    target = torch.cat([TARGET, TARGET + 1])
    mask = torch.tensor([[[True, True], [True, False], [True, True]], [[False, True], [True, True], [True, True]]])
    horizon = torch.tensor([[[1, 0], [2, 1], [3, 2]], [[0, 1], [1, 2], [2, 3]]]) if per_agent else None
    halves = [(pred[i:i + 1], target[i:i + 1], mask[i:i + 1], None if horizon is None else horizon[i:i + 1])
              for i in range(2)]
    make = lambda: HorizonMSE([1, 2, 3])  # noqa: E731
    a, ref = merged(make, halves[:1], halves[1:]), whole(make, (pred, target, mask, horizon))
    assert_same_states(a, ref)
    torch.testing.assert_close(a.compute(), ref.compute(), rtol=0, atol=0)


# -------------------------------------------------------------------------------------------- EdgeAccuracy
# Seven edge-steps, recall per true class; any type > 0 is "interaction", on either side.
EA_PRED = torch.tensor([0, 1, 2, 0, 1, 0, 0])
EA_TARGET = torch.tensor([0, 1, 1, 1, 0, 0, 3])


def test_edge_accuracy_hand_example() -> None:
    m = EdgeAccuracy()
    m.update(EA_PRED, EA_TARGET)
    # none (truth 0 at 0, 4, 5): predicted 0 at 0 and 5 -> 2/3
    # interaction (truth > 0 at 1, 2, 3, 6): predicted > 0 at 1 and 2 (type 2 counts as found) -> 2/4
    assert_values(m.compute(), [2 / 3, 0.5])


def test_edge_accuracy_mask() -> None:
    """Masked edge-steps leave both the hits and the totals."""
    mask = torch.tensor([True, True, True, False, False, True, True])  # drop a miss of each class
    m = EdgeAccuracy()
    m.update(EA_PRED, EA_TARGET, mask)
    # none: steps 0, 5 -> 2/2; interaction: steps 1, 2, 6 -> 2/3
    assert_values(m.compute(), [1.0, 2 / 3])


def test_edge_accuracy_any_shape() -> None:
    """[B, T, E] as dider.evaluation.scoring passes it: every element is an edge-step, the layout does not matter."""
    m = EdgeAccuracy()
    m.update(EA_PRED[:6].view(2, 3, 1), EA_TARGET[:6].view(2, 3, 1), torch.ones(2, 3, 1, dtype=torch.bool))
    # none: 0, 4, 5 -> 2/3; interaction: 1, 2, 3 -> 2/3
    assert_values(m.compute(), [2 / 3, 2 / 3])


def test_edge_accuracy_empty_is_nan(caplog) -> None:
    """A class with no edge-steps (no update, all masked, or only the other class) is NaN, never 0, and the
    logged values say so by name."""
    from dider.evaluation.scoring import edge_acc_values

    assert compute_quietly(EdgeAccuracy()).isnan().all()
    m = EdgeAccuracy()
    m.update(EA_PRED, EA_TARGET, torch.zeros(7, dtype=torch.bool))
    assert m.total.tolist() == [0.0, 0.0]
    assert m.compute().isnan().all()
    m = EdgeAccuracy()
    m.update(torch.tensor([0, 1]), torch.tensor([0, 0]))  # no interacting edge-step at all
    with caplog.at_level("WARNING"):
        values = edge_acc_values("test/edge_acc/prior", m)
    assert values["test/edge_acc/prior/none"].item() == 0.5 and values["test/edge_acc/prior/interaction"].isnan()
    assert "test/edge_acc/prior/interaction: reported as NaN" in caplog.text


def test_edge_accuracy_merge() -> None:
    mask = torch.tensor([True, True, False, True, True, True, True])
    a = merged(EdgeAccuracy, [(EA_PRED[:3], EA_TARGET[:3], mask[:3])], [(EA_PRED[3:], EA_TARGET[3:], mask[3:])])
    ref = whole(EdgeAccuracy, (EA_PRED, EA_TARGET, mask))
    assert_same_states(a, ref)
    # none: 0, 4, 5 -> 2/3; interaction: 1, 3, 6 (2 masked) -> 1/3
    assert_values(a.compute(), [2 / 3, 1 / 3])


# -------------------------------------------------------------------------------------------- SegmentStats
# One sample, three edges, T=5 steps.
SEG = torch.tensor([[[0, 0, 0, 0, 0],    # 0 switches
                     [0, 1, 1, 0, 0],    # 2 switches (0->1, 1->0)
                     [1, 2, 3, 3, 3]]])  # 2 switches (1->2, 2->3): every type change counts


def test_segment_stats_hand_example() -> None:
    m = SegmentStats()
    m.update(SEG)
    # 4 switches over 3 edges: 1 + 4/3 = 7/3 segments per edge; 4 per 15 edge-steps: 100 * 4/15 = 80/3
    assert_values(m.compute(), [7 / 3, 80 / 3])


def test_segment_stats_edge_mask() -> None:
    m = SegmentStats()
    m.update(SEG, torch.tensor([[True, True, False]]))
    # 2 switches over 2 edges: 1 + 1 = 2 per edge; 2 per 10 steps -> 20 per 100
    assert_values(m.compute(), [2.0, 20.0])


def test_segment_stats_empty() -> None:
    """No edges: one segment per edge (the '1 +'), zero switches per 100, not NaN."""
    assert_values(compute_quietly(SegmentStats()), [1.0, 0.0])
    m = SegmentStats()
    m.update(SEG, torch.zeros(1, 3, dtype=torch.bool))
    assert_values(m.compute(), [1.0, 0.0])


def test_segment_stats_merge() -> None:
    other = torch.tensor([[[2, 2, 0, 0, 1], [0, 0, 0, 0, 0], [1, 1, 1, 1, 1]]])  # 2 switches on edge 0
    types = torch.cat([SEG, other])
    mask = torch.tensor([[True, True, True], [True, False, True]])
    a = merged(SegmentStats, [(types[:1], mask[:1])], [(types[1:], mask[1:])])
    ref = whole(SegmentStats, (types, mask))
    assert_same_states(a, ref)
    # 4 + 2 switches over 3 + 2 edges and 25 steps: 1 + 6/5 = 2.2; 100 * 6/25 = 24
    assert_values(a.compute(), [2.2, 24.0])


# --------------------------------------------------------------------------------------------- BoundaryF1
# One edge, 10 steps -> 9 transitions; switch index i is the change between step i and i+1.
BF_TRUE = torch.tensor([[[0, 0, 1, 1, 1, 0, 0, 0, 0, 0]]])  # switches at 1 (on) and 4 (off)
BF_PRED = torch.tensor([[[0, 0, 0, 1, 1, 1, 1, 0, 2, 0]]])  # switches at 2, 6, 7, 8


def test_boundary_f1_tolerance_one() -> None:
    m = BoundaryF1(tolerance=1)
    m.update(BF_PRED, BF_TRUE)
    # predicted: 2 is within 1 of true 1; 6, 7, 8 are not (nearest true 4 is 2+ away) -> precision 1/4
    # true: 1 has predicted 2 nearby; 4 has none within 1 -> recall 1/2
    # F1 = 2 * (1/4)(1/2) / (1/4 + 1/2) = 1/3
    assert [m.pred_hit.item(), m.pred_all.item(), m.true_hit.item(), m.true_all.item()] == [1, 4, 1, 2]
    assert_values(m.compute(), 1 / 3)


def test_boundary_f1_tolerance_two() -> None:
    m = BoundaryF1(tolerance=2)
    m.update(BF_PRED, BF_TRUE)
    # predicted 2 (near 1) and 6 (|6-4| = 2) hit, 7 and 8 miss -> 2/4; both true switches found -> 2/2
    # F1 = 2 * (1/2)(1) / (3/2) = 2/3
    assert_values(m.compute(), 2 / 3)


def test_boundary_f1_tolerance_zero_and_window_edges() -> None:
    """Tolerance 0 needs the same transition; dilation near the ends of the window does not wrap around."""
    m = BoundaryF1(tolerance=0)
    m.update(torch.tensor([[[0, 1, 1, 1, 0]]]), torch.tensor([[[1, 1, 1, 1, 0]]]))
    # pred switches at 0, 3; true at 3 -> precision 1/2, recall 1/1, F1 = 2 * (1/2) / (3/2) = 2/3
    assert_values(m.compute(), 2 / 3)
    m = BoundaryF1(tolerance=1)
    m.update(torch.tensor([[[0, 0, 0, 0, 1]]]), torch.tensor([[[0, 1, 1, 1, 1]]]))
    # pred switch at 3, true at 0: 3 apart, no wrap-around from the end to the start -> F1 0
    assert_values(m.compute(), 0.0)


def test_boundary_f1_edges_do_not_match_each_other() -> None:
    """Switches are matched within their own edge and clip only (the dilation is per row)."""
    pred = torch.tensor([[[0, 0, 0, 0], [0, 1, 1, 1]], [[0, 0, 0, 0], [0, 0, 0, 0]]])  # edge 1 of clip 0: at 0
    target = torch.tensor([[[0, 1, 1, 1], [0, 0, 0, 0]], [[0, 0, 0, 0], [0, 1, 1, 1]]])  # same time, other rows
    m = BoundaryF1(tolerance=2)
    m.update(pred, target)
    # 1 predicted and 2 true switches, none in the same (clip, edge) -> precision 0, recall 0 -> F1 0
    assert [m.pred_hit.item(), m.true_hit.item()] == [0, 0]
    assert_values(m.compute(), 0.0)


def test_boundary_f1_constant_padding_does_not_count() -> None:
    """There is no mask argument: absent edges count only through their switches, so padding them with a
    constant type (as dider.evaluation.scoring's inputs do) leaves the score unchanged."""
    padded_pred = torch.cat([BF_PRED, torch.zeros_like(BF_PRED), torch.full_like(BF_PRED, 3)], dim=1)
    padded_true = torch.cat([BF_TRUE, torch.zeros_like(BF_TRUE), torch.zeros_like(BF_TRUE)], dim=1)
    a, b = BoundaryF1(tolerance=1), BoundaryF1(tolerance=1)
    a.update(BF_PRED, BF_TRUE)
    b.update(padded_pred, padded_true)
    assert_same_states(a, b)
    assert_values(b.compute(), 1 / 3)


def test_boundary_f1_empty_and_one_sided() -> None:
    """Documented: 1 when neither side has switches (also with no update); 0 when only one side has any."""
    assert_values(compute_quietly(BoundaryF1()), 1.0)
    m = BoundaryF1()
    m.update(torch.full((2, 3, 6), 2), torch.ones(2, 3, 6, dtype=L))  # constant both sides
    assert_values(m.compute(), 1.0)
    m = BoundaryF1()
    m.update(torch.zeros(1, 1, 10, dtype=L), BF_TRUE)  # nothing predicted: recall 0 -> F1 0
    assert_values(m.compute(), 0.0)
    m = BoundaryF1()
    m.update(BF_PRED, torch.zeros(1, 1, 10, dtype=L))  # nothing to find: precision 0 -> F1 0
    assert_values(m.compute(), 0.0)
    m = BoundaryF1()
    m.update(torch.zeros(0, 3, 6, dtype=L), torch.zeros(0, 3, 6, dtype=L))  # an empty batch
    assert_values(m.compute(), 1.0)


def test_boundary_f1_reads_switches_not_type_values() -> None:
    """Only where a type changes counts, on both sides: the truth's and the prediction's labels may differ."""
    m = BoundaryF1(tolerance=0)
    m.update(torch.tensor([[[0, 1, 1, 0]]]), torch.tensor([[[0, 3, 3, 0]]]))
    assert_values(m.compute(), 1.0)


def test_boundary_f1_truth_against_itself_is_one_with_several_types() -> None:
    """dider.data.trajectories allows ground-truth edge types > 1: a switch 1 -> 2 is a switch of the truth
    too (read as on/off it was not, and the truth scored 0.8 against itself)."""
    truth = torch.tensor([[[0, 1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2, 2, 0]]])
    m = BoundaryF1(tolerance=2)
    m.update(truth, truth)
    assert_values(m.compute(), 1.0)


def test_boundary_f1_one_step_window_has_no_switches() -> None:
    """T=1 has no transitions, so (as with SegmentStats) it should count as 'no switches', i.e. F1 1."""
    m = BoundaryF1()
    m.update(torch.zeros(2, 3, 1, dtype=L), torch.zeros(2, 3, 1, dtype=L))
    assert_values(m.compute(), 1.0)


def test_boundary_f1_merge() -> None:
    pred = torch.cat([BF_PRED, BF_TRUE])
    target = torch.cat([BF_TRUE, BF_TRUE])
    a = merged(lambda: BoundaryF1(tolerance=1), [(pred[:1], target[:1])], [(pred[1:], target[1:])])
    ref = whole(lambda: BoundaryF1(tolerance=1), (pred, target))
    assert_same_states(a, ref)
    # clip 0: 1/4 predicted and 1/2 true hit; clip 1 (perfect): 2/2 and 2/2
    # micro: precision 3/6, recall 3/4 -> F1 = 2 * (1/2)(3/4) / (5/4) = 3/5
    assert_values(a.compute(), 0.6)


# ----------------------------------------------------------------------------------------- PairConsistency
# One sample, three edges, four steps, 3 edge types, kinds 1 and 2 (0: not checked).
PC_TYPES = torch.tensor([[[0, 0, 2, 0],    # kind 1, all present: type 0 x3, type 2 x1
                          [1, 1, 2, 2],    # kind 2, last step absent: type 1 x2, type 2 x1
                          [2, 2, 2, 2]]])  # kind 0: not checked
PC_KIND = torch.tensor([[1, 2, 0]])
PC_PRESENT = torch.tensor([[[True] * 4, [True, True, True, False], [True] * 4]])


def test_pair_consistency_hand_example() -> None:
    m = PairConsistency(num_types=3, num_kinds=2)
    m.update(PC_TYPES, PC_KIND, PC_PRESENT)
    share, dominant, total = m.compute()
    # kind 1: 3 of 4 edge-steps in type 0 -> 0.75; kind 2: 2 of 3 in type 1 -> 2/3
    assert_values(share, [0.75, 2 / 3])
    assert dominant.tolist() == [0, 1]
    assert total.tolist() == [4.0, 3.0]
    assert m.counts.tolist() == [[3, 0, 1], [0, 2, 1]]  # kind 0's edge left nothing anywhere


def test_pair_consistency_absent_steps_do_not_count() -> None:
    """Absent steps drop out: with kind 1's type-0 steps hidden, type 2 becomes dominant."""
    present = PC_PRESENT.clone()
    present[0, 0, :2] = False
    m = PairConsistency(num_types=3)
    m.update(PC_TYPES, PC_KIND, present)
    share, dominant, total = m.compute()
    # kind 1: steps 2 (type 2) and 3 (type 0) left -> share 1/2 (a tie: the dominant type is not asserted)
    assert m.counts[0].tolist() == [1, 0, 1]
    assert total.tolist() == [2.0, 3.0]
    assert_values(share, [0.5, 2 / 3])
    present[0, 0, 3] = False
    m = PairConsistency(num_types=3)
    m.update(PC_TYPES, PC_KIND, present)
    share, dominant, total = m.compute()
    # kind 1: only step 2 (type 2) left -> share 1, dominant 2, 1 edge-step
    assert_values(share, [1.0, 2 / 3])
    assert dominant.tolist() == [2, 1]
    assert total.tolist() == [1.0, 3.0]


def test_pair_consistency_unseen_kind_is_nan() -> None:
    """Documented: share is NaN for a kind never seen (no update, only kind 0, or nothing present), with a
    zero count."""
    share, _, total = compute_quietly(PairConsistency(num_types=3))
    assert torch.isnan(share).all() and total.tolist() == [0.0, 0.0]

    m = PairConsistency(num_types=3)
    m.update(PC_TYPES, torch.tensor([[1, 0, 0]]), PC_PRESENT)  # kind 2 never occurs
    share, dominant, total = m.compute()
    assert share[0].item() == 0.75 and torch.isnan(share[1])
    assert dominant[0].item() == 0 and total.tolist() == [4.0, 0.0]

    m = PairConsistency(num_types=3)
    m.update(PC_TYPES, PC_KIND, torch.zeros_like(PC_PRESENT))
    share, _, total = m.compute()
    assert torch.isnan(share).all() and total.tolist() == [0.0, 0.0]


def test_pair_consistency_merge() -> None:
    other = torch.tensor([[[2, 2, 2, 2], [1, 0, 1, 1], [1, 1, 1, 0]]])
    types = torch.cat([PC_TYPES, other])
    kind = torch.tensor([[1, 2, 0], [1, 2, 2]])
    present = torch.cat([PC_PRESENT, torch.ones(1, 3, 4, dtype=torch.bool)])
    make = lambda: PairConsistency(num_types=3)  # noqa: E731
    a = merged(make, [(types[:1], kind[:1], present[:1])], [(types[1:], kind[1:], present[1:])])
    ref = whole(make, (types, kind, present))
    assert_same_states(a, ref)
    share, dominant, total = a.compute()
    # kind 1: [3, 0, 1] + [0, 0, 4] = [3, 0, 5] -> type 2, 5/8
    # kind 2: [0, 2, 1] + [1, 3, 0] + [1, 3, 0] = [2, 8, 1] -> type 1, 8/11
    assert a.counts.tolist() == [[3, 0, 5], [2, 8, 1]]
    assert_values(share, [5 / 8, 8 / 11])
    assert dominant.tolist() == [2, 1] and total.tolist() == [8.0, 11.0]


# -------------------------------------------------------------------------------------- HorizonDisplacement
def _displacement_example() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One sample, 3 frames, 2 agents; positions are features 0-1 (the velocities, 2-3, never count).
    Agent 0 misses by 3-4-5 triangles at every frame: distances 5, 10, 5. Agent 1 is present at frames 0
    and 1 only, off by 1 and 2."""
    pred = torch.zeros(1, 3, 2, 4)
    pred[0, :, 0, :2] = torch.tensor([[3.0, 4.0], [6.0, 8.0], [3.0, 4.0]])
    pred[0, :, 1, :2] = torch.tensor([[1.0, 0.0], [0.0, 2.0], [9.0, 9.0]])
    pred[..., 2:] = 100.0
    mask = torch.tensor([[[True, True], [True, True], [True, False]]])
    return pred, torch.zeros_like(pred), mask


def test_horizon_displacement_hand_example() -> None:
    """ADE at h: frames of horizon 1..h. h1: (5 + 1) / 2 = 3; h2: (5 + 10 + 1 + 2) / 4 = 4.5;
    h3: (5 + 10 + 5 + 1 + 2) / 5 = 4.6. FDE at h: frames of horizon h: 3, (10 + 2) / 2 = 6, 5."""
    (ade, fde) = whole(lambda: HorizonDisplacement([1, 2, 3]), _displacement_example()).compute()
    assert_values(ade, [3.0, 4.5, 4.6])
    assert_values(fde, [3.0, 6.0, 5.0])


def test_horizon_displacement_per_agent_horizons() -> None:
    """With each frame's own horizon: agent 0's frames are horizons 0 (burn-in, not scored), 1, 2; agent 1's
    1, 2, 3 (absent at 3). ADE h1 = (10 + 1) / 2 = 5.5, h2 = (10 + 5 + 1 + 2) / 4 = 4.5; FDE h2 = (5 + 2) / 2."""
    pred, target, mask = _displacement_example()
    horizon = torch.tensor([[[0, 1], [1, 2], [2, 3]]])
    (ade, fde) = whole(lambda: HorizonDisplacement([1, 2]), (pred, target, mask, horizon)).compute()
    assert_values(ade, [5.5, 4.5])
    assert_values(fde, [5.5, 3.5])


def test_horizon_displacement_empty_is_nan_merges_and_checks_horizons() -> None:
    pred = torch.ones(2, 3, 2, 4)
    never = torch.zeros(2, 3, 2, dtype=torch.bool)
    assert whole(lambda: HorizonDisplacement([1, 3]), (pred, torch.zeros_like(pred), never)).compute().isnan().all()
    mask, target = torch.rand(2, 3, 2) > 0.3, torch.randn(2, 3, 2, 4)
    first, second = [(pred[:1], target[:1], mask[:1])], [(pred[1:], target[1:], mask[1:])]
    make = lambda: HorizonDisplacement([1, 3])  # noqa: E731
    assert_same_states(merged(make, first, second), whole(make, *first, *second))
    with pytest.raises(ValueError, match="horizon 4 exceeds the 3 predicted steps"):
        HorizonDisplacement([4]).update(pred, target, mask)
    with pytest.raises(ValueError, match="each >= 1"):
        HorizonDisplacement([0])


# ------------------------------------------------------------------------------------- InteractionRunLength
def test_interaction_run_length_by_hand() -> None:
    """Runs of one non-zero type, counted per edge; a type change inside a run starts a new run; -1 (absent)
    and 0 are no run; a masked edge counts nothing. The rate is per present (>= 0) edge-step."""
    types = torch.tensor([[[0, 1, 1, 1, 0, 0],     # one run of 3
                           [2, 2, 1, 1, 1, 0],     # runs of 2 (type 2) and 3 (type 1), from t = 0
                           [-1, 1, -1, 0, 0, 1],   # two runs of 1; 4 present steps
                           [1, 1, 1, 1, 1, 1]]])   # masked below: must not count
    m = InteractionRunLength()
    m.update(types, torch.tensor([[True, True, True, False]]))
    # steps 3 + 5 + 2 = 10, runs 1 + 2 + 2 = 5 -> 2.0; present steps 6 + 6 + 4 = 16 -> rate 10 / 16
    assert m.compute().tolist() == [2.0, 10 / 16]
    m.update(torch.tensor([[[0, 0, 1, 1, 1, 1]]]))  # + 4 steps, + 1 run, + 6 present: 14 / 6 and 14 / 22
    torch.testing.assert_close(m.compute(), torch.tensor([14 / 6, 14 / 22]))
    steps = InteractionRunLength()  # a mask per edge-step: the absent step ends the run and is not counted
    steps.update(torch.tensor([[[1, 1, 1, 1]]]), torch.tensor([[[True, True, False, True]]]))
    assert steps.compute().tolist() == [1.5, 1.0]
    empty = InteractionRunLength()
    empty.update(torch.zeros(2, 3, 5, dtype=torch.long))
    length, rate = empty.compute()
    assert length.isnan() and rate.item() == 0.0


# ---------------------------------------------------------------------------------------------- OwnCut
def test_own_cut_by_hand() -> None:
    """One edge, 10 steps, tolerance 1. Own slots start at 0, 3, 5, 8; step 5 is fixed (an entry, say), so the
    own boundaries are 3 and 8. The held type changes at 3 (0 -> 1), not at 8: on_switch = 1/2. The truth
    switches at 4, 6 and 9: both own boundaries lie within a step of one (precision 1), 6 has none within a
    step (recall 2/3): F1 = 2 * 2/3 / (1 + 2/3) = 0.8."""
    slot = torch.tensor([[[0, 0, 0, 3, 3, 5, 5, 5, 8, 8]]])
    held = torch.tensor([[[0, 0, 0, 1, 1, 1, 1, 1, 1, 1]]])
    free = torch.ones(1, 1, 10, dtype=torch.bool)
    free[..., [0, 5]] = False
    truth = torch.tensor([[[0, 0, 0, 0, 1, 1, 0, 0, 0, 1]]])
    m = OwnCut(tolerance=1)
    m.update(slot, held, free, truth)
    on_switch, f1, constant = m.compute().tolist()
    assert on_switch == pytest.approx(0.5)
    assert f1 == pytest.approx(0.8)
    assert math.isnan(constant)  # this edge's truth switches: no constant edge yet
    # a true switch at a fixed step is not the plugin's to find
    free[..., 6] = False
    m = OwnCut(tolerance=1)
    m.update(slot, held, free, truth)
    assert m.compute()[1].item() == pytest.approx(1.0)


def test_own_cut_without_own_boundaries_or_truth_is_nan() -> None:
    m = OwnCut()
    m.update(torch.zeros(1, 2, 6, dtype=torch.long), torch.zeros(1, 2, 6, dtype=torch.long),
             torch.ones(1, 2, 6, dtype=torch.bool))
    assert torch.isnan(m.compute()).all()


def test_displacement_values_and_the_verdict_against_constant_velocity() -> None:
    """The model misses by 2 and 4 at horizons 1 and 2, constant velocity by 4 and 4: ADE 2, 3 against 4, 4,
    so the ratio is 0.5 and 0.75; a model that misses by 8 at horizon 2 is worse than constant velocity there."""
    target, mask = torch.zeros(1, 2, 1, 4), torch.ones(1, 2, 1, dtype=torch.bool)
    model, cv = HorizonDisplacement([1, 2]), HorizonDisplacement([1, 2])
    along_x, along_y = torch.tensor([1.0, 0, 0, 0]), torch.tensor([0, 1.0, 0, 0])
    model.update(torch.tensor([2.0, 4.0]).view(1, 2, 1, 1) * along_x, target, mask)
    cv.update(torch.tensor([4.0, 4.0]).view(1, 2, 1, 1) * along_y, target, mask)
    out = {k: float(v) for k, v in displacement_values("test", model, cv).items()}
    assert out == pytest.approx({"test/ade/h01": 2.0, "test/fde/h01": 2.0, "test/ade/h02": 3.0, "test/fde/h02": 4.0,
                                 "test/cv/ade/h01": 4.0, "test/cv/fde/h01": 4.0, "test/cv/ade/h02": 4.0,
                                 "test/cv/fde/h02": 4.0, "test/ade_vs_cv/h01": 0.5, "test/ade_vs_cv/h02": 0.75})
    text, beats = cv_verdict(out)
    assert beats and "h01 0.50x, h02 0.75x" in text
    text, beats = cv_verdict(out | {"test/ade_vs_cv/h02": 1.5})
    assert not beats and "NOT better than constant velocity at h02" in text
    text, beats = cv_verdict(out | {"test/ade_vs_cv/h01": 1.5})  # one step ahead only: judged at the longest
    assert beats and "at h02 but not at h01" in text
    assert cv_verdict({"test/mse/h01": 1.0}) is None
    assert list(leading_first(["test/mse/h01", "test/cv/ade/h01", "test/ade_vs_cv/h01", "test/ade/h01"])) == [
        "test/ade_vs_cv/h01", "test/ade/h01", "test/cv/ade/h01", "test/mse/h01"]


def test_own_boundaries_per_constant_edge_by_hand() -> None:
    """Three edges, 8 steps (step 0 fixed). Edge 0's truth never switches and it has own boundaries at 3 and 6;
    edge 1's truth never switches and it has none; edge 2's truth switches at 4 (not a constant edge): 2 own
    boundaries over 2 constant edges = 1.0."""
    slot = torch.tensor([[[0, 0, 0, 3, 3, 3, 6, 6], [0] * 8, [0, 0, 0, 0, 4, 4, 4, 4]]])
    held = torch.zeros(1, 3, 8, dtype=torch.long)
    free = torch.ones(1, 3, 8, dtype=torch.bool)
    free[..., 0] = False
    truth = torch.tensor([[[1] * 8, [0] * 8, [0, 0, 0, 0, 1, 1, 1, 1]]])
    m = OwnCut(tolerance=1)
    m.update(slot, held, free, truth)
    assert m.compute()[2].item() == pytest.approx(1.0)


def test_the_edges_verdict_by_hand() -> None:
    from dider.evaluation.scoring import edges_verdict

    assert edges_verdict({"test/ade_vs_no_edges/h01": 1.3, "test/ade_vs_no_edges/h15": 0.8}) is None
    text = edges_verdict({"test/ade_vs_no_edges/h01": 0.9, "test/ade_vs_no_edges/h15": 1.05})
    assert text.startswith("the edges do not earn their keep") and "h01 0.90x, h15 1.05x" in text
    assert edges_verdict({"test/ade/h15": 1.0}) is None
    # edges that hold no interaction: the roll-outs differ by float rounding, which is not help
    assert edges_verdict({"test/ade_vs_no_edges/h15": 0.9997}).startswith("the edges do not earn their keep")
    assert edges_verdict({"test/ade_vs_no_edges/h15": 0.994}) is None


def test_a_test_pass_compares_the_forecast_with_its_edges_off(make_cfg, tmp_path) -> None:
    """Every test pass of a model with edges rolls it out again with every edge off: the ratio of the two ADEs."""
    from dider.run import train

    metrics = train(make_cfg(["logger=none", "model=dnri"], out=tmp_path / "run"))
    for h in (1, 15, 25):
        assert metrics[f"test/ade_vs_no_edges/h{h:02d}"] > 0
    static = train(make_cfg(["logger=none", "model=static_decoder"], out=tmp_path / "static"))
    assert not any("ade_vs_no_edges" in k for k in static)


def test_edges_off_is_no_edge_even_where_type_0_sends_messages(make_cfg) -> None:
    """With ``skip_first=false`` type 0 passes messages: the no-edges roll-out is the decoder with no edge at all
    (as with ``decoder_edges`` off), not every edge held at type 0."""
    from dider.models.vae import RelationalVAE

    torch.manual_seed(0)
    net = RelationalVAE.from_config(make_cfg(["model=dnri", "model.net.decoder.skip_first=false"]).model).eval()
    x, mask = torch.rand(2, 12, 3, 4) * 2 - 1, torch.ones(2, 12, 3, dtype=torch.bool)
    zeros = torch.zeros(2, 6, 11, dtype=torch.long)
    off = net.rollout(x, mask, 5, 7, edges=zeros, edges_off=True)[0]
    assert not torch.equal(off, net.rollout(x, mask, 5, 7, edges=zeros)[0])
    net.decoder_edges = False
    assert torch.equal(off, net.rollout(x, mask, 5, 7, edges=zeros)[0])
