"""A user's own plugin and data formats, outside dider: what a checkpoint or a run folder's config may build once the
user trusts it."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import pandas as pd
import torch

from dider.data.clip_source import Clips
from dider.data.track_sources import TrackFile
from dider.models.encoder import GNNLSTMEncoder
from dider.validation import Rule


class MyEncoder(GNNLSTMEncoder):
    """DNRI's encoder under another name, as a user's package would hold one."""


def not_a_class(**settings):  # a function at a class's place: never built, even when trusted
    raise AssertionError("called")


def _one_character(value: object) -> str | None:
    return None if isinstance(value, str) and len(value) == 1 else "expected one character"


@dataclass(frozen=True)
class DelimitedTracks(TrackFile):
    """A track format of the user's own: text without a header, one row per agent per frame, the fields scene,
    agent, frame, x and y separated by ``delimiter`` (its option beside the base's path and frame_rate)."""

    delimiter: str = "\t"

    SETTINGS: ClassVar[dict[str, Rule | type]] = TrackFile.SETTINGS | {"delimiter": _one_character}

    def read(self, path: Path) -> pd.DataFrame:
        return pd.read_csv(path, sep=self.delimiter, names=["scene", "agent", "frame", "x", "y"])


@dataclass(frozen=True)
class Ramps:
    """A clip format of the user's own: ``count`` clips of 6 steps of 2 agents, ramps of consecutive numbers, as one
    part that the clips module splits by ``data.split``."""

    count: int = 20

    SPLIT_SETTINGS: ClassVar[tuple[str, ...]] = ("split", "seed")

    def clips(self, sizes: Mapping[str, int | None], cache_dir: Path) -> dict[str, Clips]:
        return {"all": Clips(torch.arange(self.count * 6 * 2 * 4, dtype=torch.float32).reshape(self.count, 6, 2, 4))}

    def where(self) -> str:
        return "the ramps"
