"""A clip source's splits made into datasets: the caps on each split's clips and the normalised, padded clips
(the normaliser itself is fitted by the data module, on the split or file its data set prescribes)."""

from __future__ import annotations

from collections.abc import Mapping

from dider.data.batch import Normalizer
from dider.data.common import ClipDataset, spread_indices
from dider.data.tracks import Clips
from dider.protocol import fill_absent


def capped(parts: Mapping[str, Clips], caps: Mapping[str, int | None]) -> dict[str, Clips]:
    """Each split's clips cut to its cap (``caps[split]``: that many evenly spread; None or no entry: all)."""
    return {split: clips.select(spread_indices(len(clips), caps.get(split))) for split, clips in parts.items()}


def clip_datasets(parts: Mapping[str, Clips], normalizer: Normalizer) -> dict[str, ClipDataset]:
    """Each split normalised, absent agents zeroed (the normalised range's centre), as a :class:`ClipDataset`
    (states [S, T, N, 4], mask [S, T, N], edges [S, T-1, E] or None, the clips' ids as its sources)."""
    out = {}
    for split, clips in parts.items():
        mask = clips.present
        out[split] = ClipDataset(fill_absent(normalizer.normalize(clips.states), mask), mask, clips.edges, clips.ids)
    return out
