"""The encoder's two per-edge LSTMs, forward and reverse, as one training-time recurrence.

ATen's CPU LSTM (oneDNN) spent ~0.5 s of a 2 s DNRI step in forward + backward over 768 edge sequences of
50 frames; on bf16 autocast it is no faster than fp32. Here the input projections of both directions are one
large matmul over every frame (the arithmetic), and the recurrence runs both directions together as one
batched [2, M, R] x [2, R, 4R] product per frame, whose element-wise gate ops stay in cache. Forward and
backward: 0.48 -> 0.39 s (fp32), 0.29 -> 0.21 s (bf16) on the 2-core CPU. The weights stay two ``nn.LSTM``
modules, so checkpoints and the one-step evaluation path (``nn.LSTM`` itself) are unchanged.
"""

from __future__ import annotations

import torch
from torch import nn


def _check(rnn: nn.LSTM) -> None:
    if rnn.num_layers != 1 or not rnn.bias or rnn.proj_size or rnn.bidirectional:
        raise ValueError("bidirectional_lstm: expects single-layer, unidirectional nn.LSTMs with biases")


def bidirectional_lstm(seq: torch.Tensor, fwd: nn.LSTM, rev: nn.LSTM) -> tuple[torch.Tensor, torch.Tensor]:
    """Run ``fwd`` over ``seq`` and ``rev`` over ``seq`` reversed in time, from zero states.

    seq: [T, M, H] time-major -> (h_fwd, h_rev), each [M, T, R]: h_fwd[:, t] has seen frames 0..t,
    h_rev[:, t] frames t..T-1. Equal to ``fwd(seq)`` and ``rev(seq.flip(0)).flip(0)`` (time-major) up to
    float rounding. The cell state is kept in fp32 under autocast.
    """
    _check(fwd)
    _check(rev)
    steps, m, _ = seq.shape
    r = fwd.hidden_size
    w_ih = torch.cat([fwd.weight_ih_l0, rev.weight_ih_l0])  # [8R, H]
    bias = torch.cat([fwd.bias_ih_l0 + fwd.bias_hh_l0, rev.bias_ih_l0 + rev.bias_hh_l0])
    gates_x = torch.addmm(bias, seq.flatten(0, 1), w_ih.T).view(steps, m, 2, 4 * r).unbind(0)
    w_hh = torch.stack([fwd.weight_hh_l0.T, rev.weight_hh_l0.T])  # [2, R, 4R]
    h: torch.Tensor | None = None
    c: torch.Tensor | None = None
    out = []
    for s in range(steps):  # direction 0 at frame s, direction 1 at frame T-1-s
        g = torch.stack([gates_x[s][:, 0], gates_x[steps - 1 - s][:, 1]])  # [2, M, 4R]
        if h is not None:
            g = torch.baddbmm(g, h, w_hh)
        g = g.float()
        sig = g.sigmoid()  # gate order i, f, g, o (nn.LSTM's); the candidate's sigmoid is unused
        i, f, _, o = sig.chunk(4, dim=-1)
        cand = g[..., 2 * r : 3 * r].tanh()
        c = i * cand if c is None else f * c + i * cand
        h = o * c.tanh()
        out.append(h)
    return torch.stack([h[0] for h in out], 1), torch.stack([h[1] for h in reversed(out)], 1)
