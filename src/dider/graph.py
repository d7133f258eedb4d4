"""Directed complete graphs over N agents: edge indexing shared by encoder, decoders and data.

Edges are the off-diagonal entries of an N x N matrix in row-major order, sender first:
for N = 3 the order is (0,1), (0,2), (1,0), (1,2), (2,0), (2,1) as (sender, receiver).
"""

from __future__ import annotations

from functools import lru_cache

import torch


@lru_cache(maxsize=256)
def _edge_index(num_agents: int, device: str) -> tuple[torch.Tensor, torch.Tensor]:
    # Built by arithmetic (no nonzero: its output shape depends on the values) directly on the
    # device, once per device and agent count: a per-call copy from the host would make every
    # training step wait for it. Normal tensors even when first asked for under inference mode (an
    # evaluation or prediction first in the process): a cached inference tensor could never be saved
    # for a later training step's backward.
    with torch.inference_mode(False):
        send = (torch.arange(num_agents, device=device).view(-1, 1)
                .expand(num_agents, max(num_agents - 1, 0)))
        other = torch.arange(max(num_agents - 1, 0), device=device).view(1, -1)
        recv = other + (other >= send).long()  # every agent but the sender, in order
        return send.reshape(-1), recv.reshape(-1)


def edge_index(num_agents: int,
               device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Sender and receiver agent index of every directed edge, each [E] long, E = N(N-1), on
    ``device`` (cached there: never copied again)."""
    return _edge_index(num_agents, str(torch.device(device)))


def num_edges(num_agents: int) -> int:
    return num_agents * (num_agents - 1)


def num_agents(num_edges: int) -> int:
    """The N with N(N-1) = ``num_edges`` (the inverse of :func:`num_edges`)."""
    return int(round((1 + (1 + 4 * num_edges) ** 0.5) / 2))


def edge_id(send: torch.Tensor, recv: torch.Tensor, num_agents: int) -> torch.Tensor:
    """Position of the directed edges send -> recv (long tensors, send != recv) in
    :func:`edge_index`'s order."""
    return send * (num_agents - 1) + recv - (recv > send).long()


def edge_mask(agent_mask: torch.Tensor) -> torch.Tensor:
    """Edges whose sender and receiver are both present.

    agent_mask: [..., N] bool -> [..., E] bool.
    """
    send, recv = edge_index(agent_mask.shape[-1], agent_mask.device)
    return agent_mask[..., send] & agent_mask[..., recv]


def pair_sum(send_values: torch.Tensor, recv_values: torch.Tensor) -> torch.Tensor:
    """For every directed edge, sender value + receiver value: two [..., N, F] -> [..., E, F]."""
    send, recv = edge_index(send_values.shape[-2], send_values.device)
    # index_select (backward: index_add): faster on the CPU than advanced indexing (backward:
    # index_put) or a dense N x N broadcast with the diagonal sliced out
    # (docs/journal/performance_history.md).
    return send_values.index_select(-2, send) + recv_values.index_select(-2, recv)


def aggregate_to_receivers(edge_values: torch.Tensor, num_agents: int) -> torch.Tensor:
    """Sum edge values over senders for each receiver: [..., E, F] -> [..., N, F]."""
    send, recv = edge_index(num_agents, edge_values.device)
    out = edge_values.new_zeros(*edge_values.shape[:-2], num_agents, edge_values.shape[-1])
    return out.index_add(out.dim() - 2, recv, edge_values)
