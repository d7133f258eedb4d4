"""Prior plugins: edge-type logits from the forward (past-only) LSTM state. h: [..., R] -> [..., K].

Logits are fp32 under autocast too: the softmaxes and KL terms computed from them lose the prior's
small probabilities in bf16.
"""

from __future__ import annotations

import math
from typing import ClassVar

import torch
from torch import nn

from dider.models.layers import head
from dider.validation import NUM_TYPES, Rule, check_settings, integer, optional, within_open


class LearnedPrior(nn.Module):
    """DNRI's learned prior: an MLP head on the forward LSTM state (conditions on x_0..x_t only)."""

    SETTINGS: ClassVar[dict[str, Rule]] = {**{k: integer(1)
                                              for k in ("rnn_hidden", "hidden", "num_layers")},
                                           "num_types": NUM_TYPES}

    def __init__(self, num_types: int, rnn_hidden: int = 64, hidden: int = 128,
                 num_layers: int = 3) -> None:
        super().__init__()
        check_settings(self, locals())
        self.net = head(rnn_hidden, hidden, num_types, num_layers)

    def forward(self, h_fwd: torch.Tensor) -> torch.Tensor:
        return self.net(h_fwd).float()


class FixedPrior(nn.Module):
    """A fixed categorical prior (NRI): ``no_edge_prob`` on type 0, the rest spread evenly.

    ``no_edge_prob: null`` gives the uniform prior.
    """

    SETTINGS: ClassVar[dict[str, Rule]] = {"num_types": NUM_TYPES,
                                           "no_edge_prob": optional(within_open(0.0, 1.0))}

    def __init__(self, num_types: int, no_edge_prob: float | None = 0.9) -> None:
        super().__init__()
        check_settings(self, locals())
        if no_edge_prob is None:
            log_probs = torch.full((num_types,), -math.log(num_types))
        else:
            log_probs = fixed_log_probs(num_types, no_edge_prob)
        self.register_buffer("log_probs", log_probs)
        self.num_types = num_types

    def forward(self, h_fwd: torch.Tensor) -> torch.Tensor:
        return self.log_probs.expand(*h_fwd.shape[:-1], self.num_types)


def fixed_log_probs(num_types: int, no_edge_prob: float) -> torch.Tensor:
    """[K] log-probabilities with ``no_edge_prob`` on type 0 and the rest spread evenly."""
    if not 0.0 < no_edge_prob < 1.0:
        raise ValueError(f"no_edge_prob={no_edge_prob}: must lie in (0, 1)")
    rest = (1.0 - no_edge_prob) / (num_types - 1)
    return torch.tensor([math.log(no_edge_prob)] + [math.log(rest)] * (num_types - 1))
