"""Encoder plugin: per-step GNN edge embedding, forward (past) and reverse (future) LSTMs per edge,
and the posterior head.

Shapes: B batch, T steps, N agents, E = N(N-1) directed edges, H GNN width, R LSTM width, K edge
types.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import nn

from dider.graph import aggregate_to_receivers, edge_mask
from dider.models.layers import MLP, PairLinear, checkpointed, head
from dider.models.rnn import bidirectional_lstm
from dider.validation import NUM_TYPES, Rule, boolean, check_settings, integer, one_of, within

LSTMState = tuple[torch.Tensor, torch.Tensor]


@dataclass
class EncoderOutput:
    """Per-edge features of the T-1 transitions t -> t+1 of a T-frame clip."""

    # [B, E, T-1, R] forward LSTM: transition t has seen x_0..x_t (the prior's input)
    h_fwd: torch.Tensor
    h_rev: torch.Tensor  # [B, E, T-1, R] reverse LSTM: transition t has seen x_{t+1}..x_{T-1}
    posterior_logits: torch.Tensor  # [B, E, T-1, K] from [h_rev, h_fwd]; fp32 under autocast too


class GNNEdgeEmbedding(nn.Module):
    """NRI/DNRI factor-graph embedding, node -> edge -> node -> edge, at every frame independently.

    x: [..., N, D], mask: [..., N] bool or None -> [..., E, H].
    """

    def __init__(self, input_dim: int = 4, hidden: int = 256, dropout: float = 0.0,
                 batch_norm: bool = True):
        super().__init__()
        self.node1 = MLP(input_dim, hidden, hidden, dropout, batch_norm)
        self.edge1_in = PairLinear(hidden, hidden)
        self.edge1 = MLP(2 * hidden, hidden, hidden, dropout, batch_norm)
        self.node2 = MLP(hidden, hidden, hidden, dropout, batch_norm)
        self.edge2_in = PairLinear(hidden, hidden, extra_dim=hidden)
        self.edge2 = MLP(3 * hidden, hidden, hidden, dropout, batch_norm)
        # The first Linear of each edge MLP lives in its PairLinear.
        del self.edge1.fc1, self.edge2.fc1

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        n = x.shape[-2]
        h = self.node1(x)
        e_skip = self.edge1.tail(self.edge1_in(h))
        if mask is None:
            h = aggregate_to_receivers(e_skip, n) / (n - 1)
        else:  # mean over present senders; absent edges contribute nothing
            em = edge_mask(mask).unsqueeze(-1).to(e_skip.dtype)
            count = aggregate_to_receivers(em, n).clamp_min(1.0)
            h = aggregate_to_receivers(e_skip * em, n) / count
        h = self.node2(h)
        return self.edge2.tail(self.edge2_in(h, e_skip))


class GNNLSTMEncoder(nn.Module):
    """DNRI's encoder: GNN embedding per step, per-edge forward and reverse LSTMs, posterior
    head."""

    SETTINGS: ClassVar[dict[str, Rule]] = {
        **{k: integer(1)
           for k in ("input_dim", "hidden", "rnn_hidden", "head_hidden", "head_layers")},
        "dropout": within(0.0, 1.0), "batch_norm": boolean, "checkpoint": boolean,
        "posterior_reads": one_of("sequence", "transition"), "num_types": NUM_TYPES}
    # non-integer settings that fix parameter shapes
    SHAPES: ClassVar[tuple[str, ...]] = ("posterior_reads",)

    def __init__(
        self,
        num_types: int,
        input_dim: int = 4,
        hidden: int = 256,
        rnn_hidden: int = 64,
        head_hidden: int = 128,
        head_layers: int = 3,
        dropout: float = 0.0,
        batch_norm: bool = True,
        checkpoint: bool = False,
        posterior_reads: str = "sequence",
    ) -> None:
        """checkpoint: in training, recompute the GNN embedding's activations in the backward pass
        instead of storing them (less memory for large scenes, one more embedding forward per step;
        same gradients). posterior_reads: what the posterior's edge type at transition t -> t+1
        reads: the whole clip (``sequence``: [h_rev, h_fwd], DNRI's) or the transition itself
        (``transition``: the past h_fwd and the embedding of frame t+1, what the edge did at that
        step, not what it will do later)."""
        super().__init__()
        check_settings(self, locals())
        self.checkpoint = checkpoint
        self.embed = GNNEdgeEmbedding(input_dim, hidden, dropout, batch_norm)
        self.forward_rnn = nn.LSTM(hidden, rnn_hidden, batch_first=True)
        self.reverse_rnn = nn.LSTM(hidden, rnn_hidden, batch_first=True)
        self.posterior_reads = posterior_reads
        head_in = 2 * rnn_hidden if posterior_reads == "sequence" else rnn_hidden + hidden
        self.posterior_head = head(head_in, head_hidden, num_types, head_layers)
        self.rnn_hidden = rnn_hidden

    def _embed(self, x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """x [B, T, N, D], mask [B, T, N] or None -> one sequence per edge, time-major: [T, B*E, H].

        The GNN runs time-major so that every frame's edge rows are contiguous for the LSTMs: no
        transposed copy forwards, and no transposed gradient into the batch norms backwards."""
        x, mask = x.transpose(0, 1), None if mask is None else mask.transpose(0, 1)
        if self.checkpoint and torch.is_grad_enabled():
            # All frames in one checkpoint, not one per frame: the batch norms' statistics span
            # every frame, and this call comes first in the forward pass, so its re-run in the
            # backward pass comes last, when the decoder's and the LSTMs' activations are already
            # freed.
            emb = checkpointed(self.embed, x, mask)  # [T, B, E, H]
        else:
            emb = self.embed(x, mask)
        return emb.flatten(1, 2)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> EncoderOutput:
        """Features of the T-1 transitions of a clip. x: [B, T, N, D], mask: [B, T, N] bool or None.

        For transition t -> t+1 the prior reads h_fwd (x_0..x_t) and the posterior reads [h_rev,
        h_fwd] where h_rev has seen x_{t+1}..x_{T-1}: unlike DNRI's released code, the posterior
        sees the state the transition produced (``posterior_reads=sequence``); with
        ``posterior_reads=transition`` it reads [h_fwd, the GNN embedding of x_{t+1}]: the
        transition and its past.
        """
        b = x.shape[0]
        # Both LSTMs over all T frames: the forward output at frame t has seen x_0..x_t, the reverse
        # output at frame t+1 has seen x_{t+1}..x_{T-1}.
        emb = self._embed(x, mask)
        h_fwd, h_rev = bidirectional_lstm(emb, self.forward_rnn, self.reverse_rnn)
        h_fwd, h_rev = h_fwd[:, :-1].unflatten(0, (b, -1)), h_rev[:, 1:].unflatten(0, (b, -1))
        if self.posterior_reads == "sequence":
            reads = torch.cat([h_rev, h_fwd], dim=-1)
        else:  # frame t+1's embedding, [T-1, B*E, H] time-major -> [B, E, T-1, H]
            reads = torch.cat(
                [h_fwd, emb[1:].transpose(0, 1).unflatten(0, (b, -1)).to(h_fwd.dtype)], dim=-1)
        logits = self.posterior_head(reads).float()  # softmax, KL and Gumbel in fp32
        return EncoderOutput(h_fwd, h_rev, logits)

    def past(self, x: torch.Tensor,
             mask: torch.Tensor | None = None) -> tuple[torch.Tensor, LSTMState]:
        """Forward LSTM only, over every given frame: x [B, T, N, D] -> h_fwd [B, E, T, R] and its
        state."""
        h_fwd, state = self.forward_rnn(self._embed(x, mask).transpose(0, 1))
        return h_fwd.unflatten(0, (x.shape[0], -1)), state

    def step(
        self, x_t: torch.Tensor, state: LSTMState | None, mask_t: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, LSTMState]:
        """Advance the forward LSTM by one frame. x_t: [B, N, D] -> h_fwd_t [B, E, R] and the new
        state."""
        # [1, B*E, H]
        seq = self._embed(x_t.unsqueeze(1), None if mask_t is None else mask_t.unsqueeze(1))
        out, state = self.forward_rnn(seq.transpose(0, 1), state)
        return out.view(x_t.shape[0], -1, self.rnn_hidden), state
