"""Building blocks: MLPs and the pair MLP whose first layer is split over sender and receiver.

A Linear on a concatenation [h_send, h_recv] equals W_s h_send + W_r h_recv. Applying the two halves
on the N node rows and gathering onto the E = N(N-1) edge rows does the expensive matmul N times per
step instead of N(N-1) times, which is where most of the encoder's and decoders' arithmetic went.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator

import torch
from torch import nn
from torch.utils.checkpoint import checkpoint

from dider.graph import pair_sum


def init_linear(layer: nn.Linear, bias: float = 0.1) -> None:
    nn.init.xavier_normal_(layer.weight)
    if layer.bias is not None:
        nn.init.constant_(layer.bias, bias)


class _ContiguousGrad(torch.autograd.Function):
    """Identity whose backward hands on a contiguous gradient."""

    @staticmethod
    def forward(ctx: object, x: torch.Tensor) -> torch.Tensor:
        return x.view_as(x)

    @staticmethod
    def backward(ctx: object, grad: torch.Tensor) -> torch.Tensor:
        return grad.contiguous()


class _Recompute:
    """Whether a checkpointed forward is being re-run for its backward (see
    :func:`checkpointed`)."""

    depth = 0


@contextlib.contextmanager
def _recomputing() -> Iterator[None]:
    _Recompute.depth += 1
    try:
        yield
    finally:
        _Recompute.depth -= 1


def checkpointed(fn: Callable[..., torch.Tensor], *args: torch.Tensor | None) -> torch.Tensor:
    """``fn(*args)`` without storing its intermediate activations: the backward pass re-runs ``fn``
    for them.

    Non-reentrant checkpointing: the RNG (dropout) and autocast state of the first run are restored
    for the re-run, so the gradients are those of the plain call. Batch norms in ``fn`` normalise
    the re-run with the same batch statistics but leave their running statistics alone: they were
    updated once, by the first run.
    """
    return checkpoint(fn, *args, use_reentrant=False,
                      context_fn=lambda: (contextlib.nullcontext(), _recomputing()))


class SumLinear(nn.Linear):
    """nn.Linear computed as products and a sum over the input features: [..., in_dim] -> [...,
    out_dim].

    MKL computes a one-output matmul (a matrix-vector product) and a matmul over a few input
    features with the CPU's vector instructions (other last bits on AVX2 and AVX-512); the sum
    rounds the same on either (tests/test_reproducibility.py). It holds [..., in_dim, out_dim]: for
    narrow layers only. The parameters are nn.Linear's: checkpoints load either way."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x.unsqueeze(-1) * self.weight.T).sum(-2) + self.bias


class FlatBatchNorm(nn.BatchNorm1d):
    """BatchNorm1d over every leading dimension: [..., F] -> [..., F].

    ATen's CPU batch-norm backward is fast on a contiguous gradient and several times slower on a
    transposed one, which a layout change downstream hands back silently; so the gradient is made
    contiguous first (timings: ``docs/journal/performance_history.md``).
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        flat = x.reshape(-1, x.shape[-1])
        if self.training and self.track_running_stats and _Recompute.depth:
            # The re-run updates throw-away copies of the running statistics, not the statistics
            # themselves (copies rather than None: the re-run must save the same tensors for
            # backward as the first run).
            out = nn.functional.batch_norm(flat, self.running_mean.clone(),
                                           self.running_var.clone(), self.weight,
                                           self.bias, True, self.momentum or 0.0, self.eps)
        else:
            out = super().forward(flat)
        return _ContiguousGrad.apply(out).view(x.shape)


class MLP(nn.Module):
    """DNRI's two-layer block: Linear -> ELU -> Dropout -> Linear -> ELU (-> BatchNorm). [..., i] ->
    [..., o]."""

    def __init__(self, in_dim: int, hidden: int, out_dim: int, dropout: float = 0.0,
                 batch_norm: bool = True):
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(in_dim, hidden), nn.Linear(hidden, out_dim)
        self.drop = nn.Dropout(dropout)
        self.bn = FlatBatchNorm(out_dim) if batch_norm else nn.Identity()
        init_linear(self.fc1)
        init_linear(self.fc2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.tail(self.fc1(x))

    def tail(self, pre: torch.Tensor) -> torch.Tensor:
        """Everything after the first Linear, given its output ``pre``."""
        h = self.drop(nn.functional.elu(pre))
        return self.bn(nn.functional.elu(self.fc2(h)))


def head(in_dim: int, hidden: int, out_dim: int, num_layers: int) -> nn.Sequential:
    """Linear/ELU stack ending in a Linear to ``out_dim`` (the prior and posterior heads)."""
    dims = [in_dim] + [hidden] * (num_layers - 1) + [out_dim]
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(dims[:-1], dims[1:], strict=True)):
        layers.append(nn.Linear(a, b))
        if i < len(dims) - 2:
            layers.append(nn.ELU())
    return nn.Sequential(*layers)


class PairLinear(nn.Module):
    """Linear([node_send, node_recv, edge_extra]) computed as node projections gathered onto edges.

    nodes: [..., N, F] and optional extra: [..., E, F_e] -> [..., E, out].
    """

    def __init__(self, node_dim: int, out_dim: int, extra_dim: int = 0) -> None:
        super().__init__()
        self.node_dim, self.out_dim = node_dim, out_dim
        self.weight = nn.Parameter(torch.empty(out_dim, 2 * node_dim + extra_dim))
        self.bias = nn.Parameter(torch.full((out_dim,), 0.1))
        nn.init.xavier_normal_(self.weight)

    def forward(self, nodes: torch.Tensor, extra: torch.Tensor | None = None) -> torch.Tensor:
        f = self.node_dim
        # One matmul for both halves on the node rows, then a broadcast sum onto the edges. The bias
        # takes the matmul's dtype: an fp32 bias would promote an autocast matmul's bf16 output to
        # fp32. The halves are split by unbind, whose backward stacks their gradients into one
        # tensor; two slices would each zero-fill a gradient of the whole [..., N, 2 x out] product
        # and add them.
        both = nodes @ torch.cat([self.weight[:, :f], self.weight[:, f : 2 * f]], dim=0).T
        send, recv = both.unflatten(-1, (2, self.out_dim)).unbind(-2)
        out = pair_sum(send + self.bias.to(both.dtype), recv)
        if extra is not None:
            out = out + extra @ self.weight[:, 2 * f :].T
        return out


class TypedLinear(nn.Module):
    """One Linear per edge type, applied to its own slice: [..., K, i] -> [..., K, o]."""

    def __init__(self, num_types: int, in_dim: int, out_dim: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(num_types, in_dim, out_dim))
        self.bias = nn.Parameter(torch.zeros(num_types, out_dim))
        bound = 1.0 / math.sqrt(in_dim)
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.weight.shape[0] == 1:  # the common K=2 skip-first case: a plain matmul, no batching
            # bias inside the matmul
            out = torch.addmm(self.bias[0], x.reshape(-1, x.shape[-1]), self.weight[0])
            return out.view(*x.shape[:-1], -1)
        return torch.einsum("...ki,kio->...ko", x, self.weight) + self.bias
