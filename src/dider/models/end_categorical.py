"""A segment's end as a categorical over the candidate ends, from hazards: its log-probabilities,
the end that evaluation reads, its KL, the encoding of an offset from the start, and the chain of
segments from step 0.

Shapes: ... any leading dims (a batch of edges, or of edges and candidate starts), T transitions; an
end categorical is [..., T+1] (the end T is the clip's).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

# A log-probability that is 0 in fp32 after exp (finite, so 0 * (log q - log p) stays 0 with its
# gradient).
IMPOSSIBLE = -1e4


# Offsets (in steps) around which a candidate end's offset from its segment's start is encoded
# (reads=remaining).
OFFSET_SCALES = tuple(2**k for k in range(7))  # 1 .. 64


def offset_features(offset: torch.Tensor) -> torch.Tensor:
    """[...] steps >= 0 -> [..., len(OFFSET_SCALES)]: Gaussian bumps on log(1 + offset) at each
    scale."""
    # made on the device (powers of two): a tensor built from host data would be a host-to-device
    # copy in every step
    centres = (torch.arange(len(OFFSET_SCALES), device=offset.device, dtype=torch.float32).exp2()
               .log1p())
    return torch.exp(-2.0 * (offset.float().log1p().unsqueeze(-1) - centres) ** 2)


def end_log_probs(logits: torch.Tensor, start: torch.Tensor, fixed: torch.Tensor,
                  value: torch.Tensor) -> torch.Tensor:
    """The categorical over a segment's end given hazards at every step.

    logits [B, E, T]: each step's hazard (a boundary there, given none since the start); start [B,
    E] long; fixed, value [B, E, T] bool: steps whose boundary is fixed, and whether it is a
    boundary. -> [B, E, T+1] log q(e): e in (start, L], L the first fixed boundary after the start
    or T (the clip's end), the mass not ended before L put on L; IMPOSSIBLE elsewhere."""
    t = logits.shape[-1]
    after = torch.arange(t, device=logits.device) > start.unsqueeze(-1)
    log_h = torch.where(fixed, torch.where(value, 0.0, IMPOSSIBLE), F.logsigmoid(logits))
    log_stay = torch.where(fixed, torch.where(value, IMPOSSIBLE, 0.0), F.logsigmoid(-logits))
    log_stay = torch.where(after, log_stay, 0.0)
    survive = log_stay.cumsum(-1)  # log P(no boundary in (start, t])
    # log P(no boundary in (start, t)), exact (no subtraction)
    before = F.pad(survive[..., :-1], (1, 0))
    log_q = torch.where(after, log_h + before, IMPOSSIBLE)
    return torch.cat([log_q, survive[..., -1:]], -1).clamp_min(IMPOSSIBLE)


def median_end(log_q: torch.Tensor) -> torch.Tensor:
    """[B, E, T+1] log q(e) -> [B, E] long: the first e with q(end <= e) >= 1/2."""
    return (log_q.exp().cumsum(-1) >= 0.5 - 1e-6).to(torch.uint8).argmax(-1)


def end_kl(log_q: torch.Tensor, log_p: torch.Tensor) -> torch.Tensor:
    """KL(q || p) of two end categoricals [B, E, T+1] (log-probabilities) -> [B, E]."""
    return (log_q.exp() * (log_q - log_p)).sum(-1)


def decided_end(logits: torch.Tensor, start: torch.Tensor, fixed: torch.Tensor, value: torch.Tensor,
                threshold: float = 0.5) -> torch.Tensor:
    """The end where it is decided: the first candidate after the start whose hazard passes
    ``threshold`` (or a fixed boundary), else the next fixed boundary or the clip's end. Arguments
    as :func:`end_log_probs`'s -> [...] long. Unlike the median of a diffuse q(end), a segment whose
    hazards stay low runs on."""
    t = logits.shape[-1]
    after = torch.arange(t, device=logits.device) > start.unsqueeze(-1)
    ends = torch.where(fixed, value, torch.sigmoid(logits) > threshold) & after
    # the clip's end closes every segment
    ends = torch.cat([ends, torch.ones_like(ends[..., :1])], -1)
    return ends.to(torch.uint8).argmax(-1)


def chain_from_zero(end: torch.Tensor) -> torch.Tensor:
    """The segments that follow each other from step 0: end [..., S] long, the end of a segment
    starting at each step s (in (s, S]; S: the clip's end) -> [..., S] bool, whether s starts one of
    them. Pointer jumping: after round j the starts reached in fewer than 2^j segments are known,
    and the pointers jump 2^j segments; ceil(log2 (S + 1)) rounds of a scatter and a gather,
    whatever the ends."""
    size = end.shape[-1]
    # [..., S+1]; the clip's end absorbs
    jump = torch.cat([end, torch.full_like(end[..., :1], size)], -1)
    reached = torch.zeros_like(jump, dtype=torch.long)
    reached[..., 0].fill_(1)
    for _ in range(max(1, math.ceil(math.log2(size + 1)))):
        reached = reached | torch.zeros_like(reached).scatter_add(-1, jump, reached).clamp(max=1)
        jump = jump.gather(-1, jump)
    return reached[..., :size].bool()
