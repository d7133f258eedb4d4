"""The encoder's two per-edge LSTMs, forward and reverse, as one training-time call.

On large inputs ATen's CPU LSTM (oneDNN) takes a large share of a DNRI step in forward + backward
(768 edge sequences of 50 frames, input width 256), and gains little under bf16 autocast. The fused
path here does the input projections of both directions as one large matmul over every frame (where
the arithmetic is) and runs the two recurrences together, one batched [2, M, R] x [2, R, 4R] product
per frame whose element-wise gate ops stay in cache. Its per-frame Python ops cost a fixed overhead,
so on small inputs (batch 8, or input width 64) ATen's bidirectional LSTM is faster;
``FUSED_MIN_WORK`` selects ATen's below a size (off by default). The timings of both paths and their
crossover: ``docs/journal/performance_history.md``. On a GPU cuDNN's LSTM runs each direction: the
fused path's per-frame launches would not pay there. The weights stay two ``nn.LSTM`` modules, so
checkpoints and the one-step evaluation path are unchanged.
"""

from __future__ import annotations

import torch
from torch import nn


def _check(rnn: nn.LSTM) -> None:
    if rnn.num_layers != 1 or not rnn.bias or rnn.proj_size or rnn.bidirectional:
        raise ValueError("bidirectional_lstm: expects single-layer, unidirectional nn.LSTMs with "
                         "biases")


# Sequences x input width from which the fused recurrence is used on the CPU. The crossover in speed
# is about 2^17, but a threshold makes a model's rounding, and so a short run's outcome, depend on
# its batch size; so by default every CPU input takes the fused path. Set 2**17 for speed on small
# batches.
FUSED_MIN_WORK = 0


def bidirectional_lstm(
    seq: torch.Tensor, fwd: nn.LSTM, rev: nn.LSTM, fused: bool | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Run ``fwd`` over ``seq`` and ``rev`` over ``seq`` reversed in time, from zero states.

    seq: [T, M, H] time-major -> (h_fwd, h_rev), each [M, T, R]: h_fwd[:, t] has seen frames 0..t,
    h_rev[:, t] frames t..T-1. Equal to ``fwd(seq)`` and ``rev(seq.flip(0)).flip(0)`` (time-major)
    up to float rounding. ``fused``: the fused recurrence (True), ATen's (False), or by device and
    size (None).
    """
    _check(fwd)
    _check(rev)
    steps, m, width = seq.shape
    if fused is None:
        fused = seq.device.type == "cpu" and m * width >= FUSED_MIN_WORK
    if not fused and seq.is_cuda:
        # cuDNN takes each LSTM's weights as one buffer: one call on both modules' weights would
        # copy them into one (and warn) every call; two calls run as fast (docs/performance.md)
        return fwd(seq)[0].transpose(0, 1), rev(seq.flip(0))[0].flip(0).transpose(0, 1)
    if not fused:
        h0 = seq.new_zeros(2, m, fwd.hidden_size)
        weights = [*fwd._flat_weights, *rev._flat_weights]
        # [T, M, 2R]
        out = torch.lstm(seq, (h0, h0), weights, True, 1, 0.0, fwd.training, True, False)[0]
        h_fwd, h_rev = out.transpose(0, 1).chunk(2, dim=-1)
        return h_fwd, h_rev
    return _fused(seq, fwd, rev)


def _fused(seq: torch.Tensor, fwd: nn.LSTM, rev: nn.LSTM) -> tuple[torch.Tensor, torch.Tensor]:
    """The fused recurrence of :func:`bidirectional_lstm`; the cell state is kept in fp32 under
    autocast."""
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
