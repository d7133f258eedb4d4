"""What the relational VAE's teacher-forced pass returns (:class:`Inference`), and the small helpers
that its callers share: a model config as a plain dict, edge types from logits.

Shapes: B batch, T frames, N agents, D features, E edges, K edge types, S segment slots, R LSTM
width.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from dider.models.segments import Segmentation


@dataclass
class Inference:
    """Result of the teacher-forced pass over a clip."""

    pred: torch.Tensor  # [B, T-1, N, D] predictions of x_1..x_{T-1}
    posterior_logits: torch.Tensor  # [B, E, S, K] per segment
    prior_logits: torch.Tensor  # [B, E, S, K] per segment
    probs: torch.Tensor  # [B, E, T-1, K] posterior probabilities held over each segment
    step_logits: torch.Tensor  # [B, E, T-1, K] per-step posterior logits (before segmentation)
    prior_step_logits: torch.Tensor  # [B, E, T-1, K] the learned prior's logits at every step
    seg: Segmentation
    h_fwd: torch.Tensor  # [B, E, T-1, R]
    present: torch.Tensor  # [B, E, T-1] bool: the edges present at each transition
    # the objective's terms per clip, name -> [B]
    terms: dict[str, torch.Tensor] = field(default_factory=dict)
    # [B] the duration plugin's fit of its online boundary model (plugins with runs of one type),
    # else None
    boundary_fit: torch.Tensor | None = None
    # [B, E, T-1] what each edge's interaction tells the decoder (nats), where an objective term
    # reads it, else None; inf where the receiver's next state is absent (nothing to score: never
    # "indifferent")
    evidence: torch.Tensor | None = None

    def posterior_types(self) -> torch.Tensor:
        """[B, E, T-1] long: the argmax type of each step's segment."""
        k = self.posterior_logits.shape[-1]
        # a comparison, not F.one_hot, whose range check synchronises with the host
        one_hot = (self.posterior_logits.argmax(-1, keepdim=True)
                   == torch.arange(k, device=self.pred.device)).float()
        return self.seg.spread(one_hot).argmax(-1)


def plain_config(cfg: DictConfig | Mapping[str, Any]) -> dict[str, Any]:
    """A model config as a plain, resolved dict (what checkpoints keep: they load with
    weights_only)."""
    return OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)


def pick_types(logits: torch.Tensor, sample: bool) -> torch.Tensor:
    """Edge types from logits [..., K] -> [...] long: a categorical draw (Gumbel-max) or the
    argmax."""
    if sample:
        logits = logits - torch.empty_like(logits).exponential_().log()  # + Gumbel noise
    return logits.argmax(-1)
