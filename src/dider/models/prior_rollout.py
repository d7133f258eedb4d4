"""Scheduled sampling for the online prior: what the prior (the type head and the boundary model) reads in training.

Online, past the burn-in, the forward LSTM that the prior reads is advanced on the model's own predictions, not on
the truth (:meth:`RelationalVAE.rollout`). With ``prior_rollout`` set, a share of each training batch's clips
gives the prior the same kind of frames: the decoder's roll-out from the burn-in under the posterior's edges
(detached; the edges the prior is fitted to, so the rolled-out states show the interactions the posterior names).
The share rises linearly from 0 at ``prior_rollout`` (a share of training) to 1 at its end. The posterior, the
decoder and the segment ends' duration KL still read the true frames.

Shapes: B batch, T frames, N agents, D features, E edges, R LSTM width.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from dider.models.plugins import Progress
from dider.protocol import burn_in_mask, fill_absent

if TYPE_CHECKING:
    from dider.models.vae import RelationalVAE


def rollout_share(start: float | None, progress: Progress) -> float | torch.Tensor:
    """The share of clips whose prior reads the roll-out at ``progress``: 0 before ``start`` (a share of training),
    then rising linearly to 1 at the end; 0 without ``start`` or where the run's length is unknown (a trained model,
    a pass outside a Trainer). A graphed step reads it from ``progress.values`` (``prior_rollout``)."""
    if start is None:
        return 0.0
    f = progress.fraction if progress.total else 0.0
    return progress.value("prior_rollout", max(0.0, f - start) / max(1.0 - start, 1e-9))


@torch.no_grad()
def rolled_frames(model: RelationalVAE, x: torch.Tensor, mask: torch.Tensor, edges: torch.Tensor, burn_in: int,
                  mode: str) -> torch.Tensor:
    """The frames the forward LSTM reads in a roll-out of the whole clip from ``burn_in`` under given ``edges``:
    x [B, T, N, D], mask [B, T, N], edges [B, E, T-1] long -> [B, T, N, D]: the truth before the roll-out (and, in
    ``per_agent`` mode, each agent's own burn-in frames), the decoder's predictions after it."""
    t = x.shape[1]
    pred, _ = model.rollout(x, mask, burn_in, t - burn_in, mode, edges=edges)  # x_burn_in .. x_{T-1}
    frames = torch.cat([x[:, :burn_in], pred.to(x.dtype)], dim=1)
    if mode == "per_agent":  # as the roll-out feeds them: the truth in an agent's own burn-in, absent agents zeroed
        frames = fill_absent(torch.where(burn_in_mask(mask, burn_in)[..., None], x, frames), mask)
    return frames


def prior_features(model: RelationalVAE, x: torch.Tensor, mask: torch.Tensor, plugin_mask: torch.Tensor | None,
                   h_fwd: torch.Tensor, edges: torch.Tensor, share: float | torch.Tensor, burn_in: int | None,
                   mode: str) -> torch.Tensor:
    """What the online prior reads in a training pass: h_fwd [B, E, T-1, R] (the forward LSTM over the true
    frames), or for a ``share`` of the clips the forward LSTM over :func:`rolled_frames` -> [B, E, T-1, R]."""
    if not model.training or burn_in is None or not 1 <= burn_in < x.shape[1]:
        return h_fwd
    if isinstance(share, float) and share <= 0.0:
        return h_fwd
    rolled = rolled_frames(model, x, mask, edges, burn_in, mode)
    chosen = torch.rand(x.shape[0], 1, 1, 1, device=x.device) < share  # which clips read the roll-out
    h, _ = model.encoder.past(torch.where(chosen, rolled, x), plugin_mask)
    return h[:, :, :-1]
