"""Structure recovery as the relational-inference field scores it on NRI's systems: edge accuracy
with the learned types matched to the true labels, and the AUROC of the edge probabilities.

A model's type numbers are arbitrary (an unsupervised model may learn "spring" as type 0), so NRI
and its followers score the best one-to-one matching of types to labels: the permutation for two
types, the Hungarian algorithm for more. The accuracy with type k read as label k is reported beside
it, so a matching that hides a model's own labelling is seen.
"""

from __future__ import annotations

import torch
from torchmetrics import Metric
from torchmetrics.functional.classification import binary_auroc
from torchmetrics.utilities import dim_zero_cat


def best_assignment(score: list[list[float]]) -> list[int]:
    """The one-to-one assignment of rows to columns of a square matrix with the largest total score
    (the Hungarian algorithm with row and column potentials, O(n^3)): ``col[i]`` for each row i."""
    n = len(score)
    inf = float("inf")
    cost = [[-s for s in row] for row in score]
    # potentials of rows and columns (1-based; 0 is a sentinel)
    u, v = [0.0] * (n + 1), [0.0] * (n + 1)
    owner, came_from = [0] * (n + 1), [0] * (n + 1)  # owner[j]: the row assigned to column j
    for row in range(1, n + 1):
        owner[0], free_col = row, 0
        slack, seen = [inf] * (n + 1), [False] * (n + 1)
        while owner[free_col]:  # grow the alternating tree until it reaches an unassigned column
            seen[free_col] = True
            r, delta, nxt = owner[free_col], inf, 0
            for j in range(1, n + 1):
                if not seen[j]:
                    reduced = cost[r - 1][j - 1] - u[r] - v[j]
                    if reduced < slack[j]:
                        slack[j], came_from[j] = reduced, free_col
                    if slack[j] < delta:
                        delta, nxt = slack[j], j
            for j in range(n + 1):
                if seen[j]:
                    u[owner[j]] += delta
                    v[j] -= delta
                else:
                    slack[j] -= delta
            free_col = nxt
        while free_col:  # flip the path's assignments back to the root
            prev = came_from[free_col]
            owner[free_col] = owner[prev]
            free_col = prev
    col = [0] * n
    for j in range(1, n + 1):
        col[owner[j] - 1] = j - 1
    return col


def match_types(confusion: torch.Tensor) -> torch.Tensor:
    """confusion [K, C] (learned type x true label counts) -> [K] long: the label each type is
    matched to (-1: a type left unmatched when K > C), maximising the matched counts."""
    k, c = confusion.shape
    n = max(k, c)
    square = torch.zeros(n, n, dtype=torch.float64)
    square[:k, :c] = confusion.double().cpu()
    col = torch.tensor(best_assignment(square.tolist()))[:k]
    return torch.where(col < c, col, -1)


class StructureRecovery(Metric):
    """Edge-step accuracy of learned types against true labels, matched (module docstring) and as
    labelled, and the AUROC of the probability of an edge (every type not matched to label 0)
    against the truth's label > 0.

    update(pred [...] long, target [...] long, mask [...] bool or None, probs [..., K] or None);
    compute() -> {"matched", "as_labelled", "auroc"} (auroc only when probs were given; NaN when the
    test split holds one class only). Labels >= K are counted in a column of their own, which no
    type can be matched to.
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False

    def __init__(self, num_types: int, **kwargs) -> None:
        super().__init__(**kwargs)
        self.num_types = num_types
        self.add_state("confusion", torch.zeros(num_types, num_types + 1, dtype=torch.float64),
                       dist_reduce_fx="sum")
        self.add_state("probs", [], dist_reduce_fx="cat")
        self.add_state("labels", [], dist_reduce_fx="cat")

    def update(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
               probs: torch.Tensor | None = None) -> None:
        keep = torch.ones_like(target, dtype=torch.bool) if mask is None else mask
        k = self.num_types
        truth = target.clamp(max=k)[keep]
        self.confusion += (torch.bincount(pred[keep] * (k + 1) + truth, minlength=k * (k + 1))
                           .view(k, k + 1).double())
        if probs is not None:
            self.probs.append(probs[keep].float())
            self.labels.append(truth)

    def compute(self) -> dict[str, torch.Tensor]:
        total = self.confusion.sum()
        label_of = match_types(self.confusion[:, : self.num_types]).to(self.confusion.device)
        rows = torch.arange(self.num_types, device=self.confusion.device)
        hits = torch.where(label_of >= 0, self.confusion[rows, label_of.clamp_min(0)], 0.0)
        out = {"matched": hits.sum() / total,
               "as_labelled": self.confusion[rows, rows].sum() / total}
        if len(self.probs):
            probs, labels = dim_zero_cat(self.probs), dim_zero_cat(self.labels)
            edge_types = (label_of != 0).to(probs.device)
            score = (probs * edge_types).sum(-1)
            truth = (labels > 0).long()
            out["auroc"] = (binary_auroc(score, truth) if 0 < int(truth.sum()) < len(truth)
                            else torch.tensor(float("nan"), device=score.device))
        return {k: v.float() for k, v in out.items()}
