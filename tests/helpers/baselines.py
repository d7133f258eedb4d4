"""Reference forecasts that a trained model must beat."""

import torch

from dider.data.batch import Normalizer


def constant_velocity(states: torch.Tensor, burn_in: int, normalizer: Normalizer) -> torch.Tensor:
    """Roll x_{t+1} = x_t + v_t, v_{t+1} = v_t from the last burn-in frame, in raw units.

    states: [B, T, N, 4] normalised -> [B, T - burn_in, N, 4] normalised predictions.
    """
    cur = normalizer.denormalize(states[:, burn_in - 1])
    preds = []
    for _ in range(states.shape[1] - burn_in):
        cur = torch.cat([cur[..., :2] + cur[..., 2:], cur[..., 2:]], dim=-1)
        preds.append(cur)
    return normalizer.normalize(torch.stack(preds, dim=1))
