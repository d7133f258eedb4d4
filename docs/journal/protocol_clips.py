"""The test clips of the synthetic standard protocol (seed 1) for a trained model, normalised as it was trained: what
the journal's diagnosis scripts read."""

import argparse
from typing import Any

import torch

import dider
from dider.data.clips import ClipsDataModule

LOADER = {"batch_size": 16, "eval_batch_size": 256}  # data=synth's loader


def protocol_clips(model_name: str, clips: int, cache: str) -> tuple[Any, torch.nn.Module, dict[str, torch.Tensor]]:
    """-> (the trained model, its network in eval mode, one batch of the first ``clips`` test clips)."""
    torch.set_num_threads(1)
    model = dider.load(model_name)
    dm = ClipsDataModule(source={"reader": "push", "seed": 1}, num_train=32, num_val=8, num_test=clips, cache_dir=cache,
                         loader=LOADER)
    dm.use_normalizer(model.normalizer)
    dm.setup()
    test = dm.datasets["test"]
    return model, model.network.eval(), test.__getitems__(list(range(len(test))))


def clips_from_command_line(description: str, model: str | None = None
                            ) -> tuple[argparse.Namespace, Any, torch.nn.Module, dict[str, torch.Tensor]]:
    """The journal scripts' command line (--model, --out, --clips, --cache; ``model``: --model's default, None:
    required) -> (its arguments, then :func:`protocol_clips`'s three)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--model", default=model, required=model is None)
    parser.add_argument("--out", required=True)
    parser.add_argument("--clips", type=int, default=300)
    parser.add_argument("--cache", default="/tmp/leads_cache")
    args = parser.parse_args()
    return args, *protocol_clips(args.model, args.clips, args.cache)
