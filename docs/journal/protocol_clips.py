"""The test clips of the synthetic standard protocol (seed 1) for a trained model, normalised as it was trained: what
the journal's diagnosis scripts read."""

from typing import Any

import torch

import dider
from dider.data.synth import SynthDataModule


def protocol_clips(model_name: str, clips: int, cache: str) -> tuple[Any, torch.nn.Module, dict[str, torch.Tensor]]:
    """-> (the trained model, its network in eval mode, one batch of the first ``clips`` test clips)."""
    torch.set_num_threads(1)
    model = dider.load(model_name)
    dm = SynthDataModule(num_train=32, num_val=8, num_test=clips, seed=1, cache_dir=cache)
    dm.use_normalizer(model.normalizer)
    dm.setup()
    test = dm.datasets["test"]
    return model, model.network.eval(), test.__getitems__(list(range(len(test))))
