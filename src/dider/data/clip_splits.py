"""The three splits, and a clip source's parts made into datasets: the splits of a file of clips or of a table's
windows (seeded fractions), recordings split in order (counts or fractions), a validation split carved from the
training clips, the caps on each split's clips, the normaliser's ranges and the normalised, padded clips."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch

from dider.data.batch import Normalizer
from dider.data.clip_source import Clips
from dider.data.common import ClipDataset, spread_indices
from dider.protocol import fill_absent
from dider.validation import integer

RANGES = ("separate", "same", "none")  # data.normalization
SPLIT_SEED = integer(-(2**63) + 1, " (magnitude < 2**63)", 2**63 - 1)  # data.seed: the split's permutation


def fractions_problem(fractions: object) -> str | None:
    """The rule of ``data.split``: three positive fractions (train, val, test) summing to 1."""
    ok = isinstance(fractions, Sequence) and len(fractions) == 3 \
        and all(isinstance(f, (int, float)) and f > 0 for f in fractions) and abs(sum(fractions) - 1) <= 1e-6
    return None if ok else "three positive fractions (train, val, test) summing to 1"


def split_indices(num: int, fractions: Sequence[float], seed: int) -> dict[str, torch.Tensor]:
    """Seeded train / val / test index sets of range(num) (``fractions`` as :func:`fractions_problem` asks); val and
    test get >= 1 clip each."""
    val, test = (max(1, round(f * num)) for f in fractions[1:])
    if num - val - test < 1:
        raise ValueError(f"data.split={list(fractions)}: {num} clips are too few for train, val and test")
    perm = torch.randperm(num, generator=torch.Generator().manual_seed(seed))
    parts = {"train": perm[val + test:], "val": perm[:val], "test": perm[val:val + test]}
    return {k: v.sort().values for k, v in parts.items()}


def carve(num: int, fraction: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Reproducible (keep, carved) index split of range(num): ``round(fraction * num)`` (>= 1) carved."""
    take = max(1, round(fraction * num))
    if take >= num:
        raise ValueError(f"data.val_fraction={fraction}: carving {take} of {num} training clips leaves none")
    perm = torch.randperm(num, generator=torch.Generator().manual_seed(seed))
    return perm[take:].sort().values, perm[:take].sort().values


def capped(parts: Mapping[str, Clips], caps: Mapping[str, int | None]) -> dict[str, Clips]:
    """Each split's clips cut to its cap (``caps[split]``: that many evenly spread; None or no entry: all)."""
    return {split: clips.select(spread_indices(len(clips), caps.get(split))) for split, clips in parts.items()}


def fit_ranges(clips: Clips, ranges: str) -> Normalizer:
    """The normaliser of ``clips``' present agents: positions and velocities each to [-1, 1] by their own scalar
    min and max (``separate``, NRI's and DNRI's), by one range for all four features (``same``, DNRI's
    ``--same_data_norm``), or the identity (``none``)."""
    if ranges == "none":
        return Normalizer((-1.0, 1.0), (-1.0, 1.0), clips.origin)
    if ranges == "same":
        values = clips.states if clips.mask is None else clips.states[clips.mask]
        if values.numel() == 0:
            raise ValueError("no present agent states to fit on")
        lo, hi = values.min().item(), values.max().item()
        return Normalizer((lo, hi), (lo, hi), clips.origin)
    return Normalizer.fit(clips.states, clips.mask, clips.origin)


def clip_datasets(parts: Mapping[str, Clips], normalizer: Normalizer) -> dict[str, ClipDataset]:
    """Each split normalised (relative to the normaliser's origin), absent agents zeroed (the normalised range's
    centre), as a :class:`ClipDataset` (states [S, T, N, 4], mask [S, T, N], edges [S, T-1, E] or None, the clips'
    ids as its sources)."""
    out = {}
    for split, clips in parts.items():
        clips = clips.relative_to(normalizer.origin)
        mask = clips.present
        out[split] = ClipDataset(fill_absent(normalizer.normalize(clips.states), mask), mask, clips.edges, clips.ids)
    return out


def counts_problem(split: object) -> str | None:
    """The rule of ``data.split`` for scenes split in order (recordings): three counts (integers >= 1, e.g. DNRI's
    [19, 7, 7]) or three fractions (all in (0, 1), e.g. [0.6, 0.2, 0.2])."""
    if not (isinstance(split, Sequence) and not isinstance(split, str) and len(split) == 3
            and all(isinstance(f, (int, float)) and not isinstance(f, bool) for f in split)):
        return "expected three numbers (train, val, test): recording counts or fractions"
    if all(0 < f < 1 for f in split) or all(math.isfinite(f) and f >= 1 and f == int(f) for f in split):
        return None
    return "give recording counts (integers >= 1) or fractions (all in (0, 1))"


def split_problem(split: object) -> str | None:
    """The form of ``data.split`` any data set of long tracks reads (the preflight's rule; its source checks which):
    fractions (a table's) or counts or fractions in order (recordings); null: the source's."""
    if split is None or fractions_problem(split) is None or counts_problem(split) is None:
        return None
    return "three fractions of a table's scenes summing to 1, or recordings in order (counts or fractions)"


def split_counts(split: Sequence[float], available: int) -> tuple[int, int, int]:
    """Recordings per split in order (``split`` as :func:`counts_problem` asks) of ``available``: fractions give val
    and test at least one each, train the rest; counts may leave recordings unused."""
    if why := counts_problem(split):
        raise ValueError(f"data.split={list(split) if isinstance(split, Sequence) else split!r}: {why}")
    if all(0 < float(s) < 1 for s in split):
        val, test = (max(1, round(float(s) * available)) for s in split[1:])
        counts = (available - val - test, val, test)
    else:
        counts = tuple(int(s) for s in split)
    if min(counts) < 1:
        raise ValueError(f"data.split={list(split)}: every split needs >= 1 recording (got {list(counts)} "
                         f"from {available} recordings)")
    if sum(counts) > available:
        raise ValueError(f"data.split={list(split)} asks for {sum(counts)} recordings but only {available} "
                         f"were found")
    return counts  # type: ignore[return-value]
