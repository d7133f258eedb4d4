"""The 3-particle push system as a clip source (``data=synth``): each split generated from its own seed
(:func:`~dider.data.simulate.simulate_push`), cached under the cache folder by every setting that made it, so a
changed ``num_test`` never changes the training clips."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, ClassVar

from dider.data.cache import cache_key, cached_splits
from dider.data.clip_source import Clips
from dider.data.common import SPLITS
from dider.data.simulate import PUSH_SHAPES, simulate_push
from dider.validation import Rule, check_settings, finite, integer, one_of

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Push:
    """What the simulation depends on: ``data=synth``'s ``data.source`` node (the split sizes are ``data.num_train``,
    ``num_val`` and ``num_test``)."""

    reader: str = "push"
    num_steps: int = 50  # frames per clip
    push_factor: float = 0.05  # the push's strength
    # the push's shape inside the radius: linear (DNRI's: fading in and out) or step (on and off at once: a positive
    # control for segment boundaries; dider.data.simulate.simulate_push)
    push: str = "linear"
    seed: int = 1  # the data seed (the top-level seed drives the model and training); split i draws from seed*1000+i

    GENERATED: ClassVar[bool] = True  # data.num_* are the splits' sizes

    SETTINGS: ClassVar[dict[str, Rule]] = {
        "reader": one_of("push"), "num_steps": integer(2), "push_factor": finite, "push": one_of(*PUSH_SHAPES),
        "seed": integer(-(2**53) + 1, " (magnitude < 2**53)", 2**53 - 1)}

    def __post_init__(self) -> None:
        check_settings(self, asdict(self), key="data.source")

    def clips(self, sizes: Mapping[str, int], cache_dir: Path) -> dict[str, Clips]:
        return read(self, sizes, cache_dir)

    def where(self) -> str:
        return "the push simulation"


CLIPS = Push  # a clip source: data.source.reader=push


def cache_params(s: Push, split: str, size: int) -> dict[str, Any]:
    """Everything that makes a split's clips: its cache key (the linear push's files predate the ``push`` key)."""
    shape = {} if s.push == "linear" else {"push": s.push}
    return {"kind": "push", "split": split, "num_samples": size, "num_steps": s.num_steps,
            "push_factor": s.push_factor, "seed": s.seed * 1000 + SPLITS.index(split), "version": 1, **shape}


def cache_path(s: Push, split: str, size: int, cache_dir: Path) -> Path:
    return cache_dir / f"synth_{split}_{cache_key(cache_params(s, split, size))}.pt"


def read(s: Push, sizes: Mapping[str, int], cache_dir: Path) -> dict[str, Clips]:
    """Each split of ``sizes`` (split -> number of clips), from the cache or simulated and cached."""

    def build(split: str, size: int, path: Path) -> dict[str, Any]:
        p = cache_params(s, split, size)
        log.info("generating %d synthetic %s clips -> %s", size, split, path)
        states, edges = simulate_push(size, s.num_steps, s.push_factor, seed=p["seed"], shape=s.push)
        return {"states": states, "edges": edges, "params": p}

    blobs = cached_splits(sizes, lambda split, size: cache_path(s, split, size, cache_dir), build)
    # edges[t] produced state t from t-1, so the transition t -> t+1 is labelled by edges[t+1].
    return {split: Clips(b["states"], edges=b["edges"][:, 1:]) for split, b in blobs.items()}
