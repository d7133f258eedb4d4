"""Small networks and random clips for the model tests."""

from __future__ import annotations

import torch

from dider.models.vae import RelationalVAE


def build(make_cfg, *overrides: str) -> RelationalVAE:
    """The network of the test config (the ``make_cfg`` fixture) with these overrides, its weights drawn from
    seed 0."""
    torch.manual_seed(0)
    return RelationalVAE.from_config(make_cfg(list(overrides)).model)


def clip(b: int = 4, t: int = 30, n: int = 3, seed: int = 0) -> dict[str, torch.Tensor]:
    """A random batch of clips: ``states`` [b, t, n, 4] uniform in [-1, 1], ``mask`` [b, t, n] all present."""
    g = torch.Generator().manual_seed(seed)
    return {"states": torch.rand(b, t, n, 4, generator=g) * 2 - 1, "mask": torch.ones(b, t, n, dtype=torch.bool)}
