"""Structure recovery as NRI scores it: types matched to labels (Hungarian), and the AUROC of the edges."""

import itertools

import pytest
import torch

from dider.evaluation.structure import StructureRecovery, best_assignment, match_types


def test_the_assignment_is_the_best_permutation():
    g = torch.Generator().manual_seed(0)
    for n in range(1, 7):
        for _ in range(30):
            score = torch.randint(0, 20, (n, n), generator=g).double()
            col = best_assignment(score.tolist())
            best = max(sum(score[i, p[i]] for i in range(n)) for p in itertools.permutations(range(n)))
            assert sorted(col) == list(range(n)) and sum(score[i, col[i]] for i in range(n)) == best


def test_match_types_by_hand():
    # three learned types, two labels: type 2 holds most of label 0, type 0 of label 1; type 1 is left over
    confusion = torch.tensor([[1.0, 9.0], [2.0, 2.0], [8.0, 0.0]])
    assert match_types(confusion).tolist() == [1, -1, 0]
    assert match_types(torch.tensor([[0.0, 5.0], [5.0, 0.0]])).tolist() == [1, 0]


def test_matched_accuracy_and_auroc_by_hand():
    m = StructureRecovery(2)
    pred = torch.tensor([1, 1, 0, 0, 1])  # the model calls "no edge" type 1
    target = torch.tensor([0, 0, 1, 1, 1])
    probs = torch.tensor([[0.2, 0.8], [0.3, 0.7], [0.9, 0.1], [0.6, 0.4], [0.5, 0.5]])
    m.update(pred, target, None, probs)
    out = m.compute()
    # matched: type 1 -> label 0, type 0 -> label 1: 4 of 5 right; as labelled: 1 of 5
    assert out["matched"] == pytest.approx(0.8) and out["as_labelled"] == pytest.approx(0.2)
    # P(edge) = P(type 0): edges score 0.9, 0.6, 0.5, non-edges 0.2, 0.3 -> every pair ordered right
    assert out["auroc"] == pytest.approx(1.0)
    m.reset()
    m.update(pred, target, None, torch.tensor([[0.2, 0.8], [0.55, 0.45], [0.9, 0.1], [0.5, 0.5], [0.4, 0.6]]))
    # positives 0.9, 0.5, 0.4 against negatives 0.2, 0.55: 2 + 1 + 1 of 6 pairs ordered right
    assert m.compute()["auroc"] == pytest.approx(4 / 6)


def test_masks_out_of_range_labels_and_one_class():
    m = StructureRecovery(2)
    pred, target = torch.tensor([[0, 1, 1]]), torch.tensor([[0, 1, 2]])
    m.update(pred, target, torch.tensor([[True, True, True]]))
    out = m.compute()
    # label 2 has no type to match: counted, always wrong
    assert out["matched"] == pytest.approx(2 / 3) and "auroc" not in out
    m = StructureRecovery(2)
    m.update(torch.tensor([0, 1]), torch.tensor([1, 1]), torch.tensor([True, False]), torch.tensor([[0.5, 0.5],
                                                                                                  [0.1, 0.9]]))
    out = m.compute()
    assert out["matched"] == 1.0 and torch.isnan(out["auroc"])  # one edge-step kept, one class: no AUROC
