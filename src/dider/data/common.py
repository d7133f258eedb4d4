"""Pieces shared by every data module: in-memory clip datasets, padding, config checks, the loaders API.

Shapes: S clips, T steps, N agents, P packed agent rows (one per agent per clip), E = N(N-1) edges.

Source identifiers: a dataset may carry, per clip, where it came from, so that results can be traced back
to the input. Batches then hold ``source``, a dict of long tensors: ``clip`` [B] (the clip's index in the
input: its position in the file, or the window's number in reading order), and optionally ``scene`` [B]
(recording or scene id), ``frame`` [B] (the input's frame number of the clip's first step) and ``agent``
[B, N] (the input's agent or track ids, -1 for padded agents). A data module whose ids are strings keeps
their names in ``source_names`` (key -> list indexed by the id).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, ClassVar

import lightning as L
import torch
import torch.distributed as dist
from lightning.pytorch.overrides.distributed import UnrepeatedDistributedSampler
from torch.utils.data import DataLoader, Dataset, RandomSampler

from dider.data.batch import Batch, Normalizer
from dider.data.loader import Loader
from dider.data.pairs import pair_kind_matrix
from dider.validation import ClassNode, Rule, integer, optional, text

SPLITS = ("train", "val", "test")
# The per-agent features of every batch, in order (raw units before normalisation).
FEATURES = ("x", "y", "vx", "vy")


def default_cache_dir() -> Path:
    return Path(os.environ.get("DIDER_CACHE", Path.home() / ".cache" / "dider"))


def select_sources(sources: dict[str, torch.Tensor] | None, idx: torch.Tensor) -> dict[str, torch.Tensor] | None:
    """The source identifiers (module docstring) of the clips ``idx`` [K] long."""
    return None if sources is None else {k: v[idx] for k, v in sources.items()}


class ClipDataset(Dataset):
    """Clips held in memory. states: [S, T, N, 4]; mask: [S, T, N] bool; edges: [S, T-1, E] long or None;
    sources: the clips' source identifiers (module docstring), each [S] or [S, N] long, or None."""

    def __init__(self, states: torch.Tensor, mask: torch.Tensor, edges: torch.Tensor | None = None,
                 sources: dict[str, torch.Tensor] | None = None) -> None:
        self.states, self.mask, self.edges, self.sources = states, mask, edges, sources
        self.everyone = bool(mask.all())  # every agent present in every clip: the batches say so (``everyone``)

    def __len__(self) -> int:
        return self.states.shape[0]

    def to(self, device: torch.device | str) -> ClipDataset:
        """The clips moved to ``device`` (a GPU the model trains on: batches are then gathered there, with no copy
        from the host a step but the batch's indices)."""
        self.states, self.mask = self.states.to(device), self.mask.to(device)
        self.edges = None if self.edges is None else self.edges.to(device)
        self.sources = None if self.sources is None else {k: v.to(device) for k, v in self.sources.items()}
        return self

    def __getitems__(self, indices: Sequence[int]) -> Batch:
        """A batch in one gather per array (the DataLoader calls it with a batch's indices), with ``everyone``:
        whether every agent of the batch is present, known on the host (no look at the mask on the device)."""
        idx = torch.as_tensor(indices, dtype=torch.long)
        if idx.device != self.states.device:  # from pinned memory, asynchronously: the host does not wait for it
            idx = idx.pin_memory().to(self.states.device, non_blocking=True)
        batch: Batch = {"states": self.states[idx], "mask": self.mask[idx], "everyone": self.everyone}
        if self.edges is not None:
            batch["edges"] = self.edges[idx]
        if self.sources is not None:
            batch["source"] = select_sources(self.sources, idx)
        return batch

    def __getitem__(self, i: int) -> Batch:
        item: Batch = {"states": self.states[i], "mask": self.mask[i]}
        if self.edges is not None:
            item["edges"] = self.edges[i]
        if self.sources is not None:
            item["source"] = {k: v[i] for k, v in self.sources.items()}
        return item


class PackedClipDataset(Dataset):
    """Clips with a different number of agents each, stored without padding.

    states: [P, T, 4] (one row per agent per clip), mask: [P, T] bool, offsets: [S+1] long, so clip i owns
    rows offsets[i]:offsets[i+1] (agent order inside a clip is kept). Batches are gathered in one
    vectorised step by ``__getitems__`` (the DataLoader calls it with a whole batch of indices) and padded
    to the largest agent count in the batch; padded agents have mask False and zero states.
    """

    def __init__(self, states: torch.Tensor, mask: torch.Tensor, offsets: torch.Tensor,
                 pairs: dict[str, torch.Tensor] | None = None, sources: dict[str, torch.Tensor] | None = None,
                 agent_ids: torch.Tensor | None = None) -> None:
        """pairs: optional packed agent pairs of each clip (:func:`dider.data.pairs.find_pairs`); batches then
        carry ``pair_kind`` [B, E] for the consistency check. sources: per-clip identifiers, each [S] long;
        agent_ids: [P] long, each row's agent id in the input; batches then carry ``source`` (module
        docstring), with ``agent`` [B, N_max] from agent_ids."""
        if states.shape[0] != mask.shape[0] or int(offsets[-1]) != states.shape[0]:
            raise ValueError(f"PackedClipDataset: {states.shape[0]} rows, mask {mask.shape[0]}, offsets end "
                             f"{int(offsets[-1])}: these must agree")
        if pairs is not None and len(pairs["pair_offsets"]) != len(offsets):
            raise ValueError(f"PackedClipDataset: pair_offsets has {len(pairs['pair_offsets'])} entries, "
                             f"offsets {len(offsets)}: these must agree")
        self.states, self.mask, self.offsets, self.pairs = states, mask, offsets, pairs
        self.sources, self.agent_ids = sources, agent_ids

    def __len__(self) -> int:
        return self.offsets.shape[0] - 1

    @property
    def num_agents(self) -> torch.Tensor:
        """Agents per clip, [S] long."""
        return self.offsets[1:] - self.offsets[:-1]

    def __getitem__(self, i: int) -> Batch:
        lo, hi = int(self.offsets[i]), int(self.offsets[i + 1])
        return {"states": self.states[lo:hi].transpose(0, 1), "mask": self.mask[lo:hi].transpose(0, 1)}

    def __getitems__(self, indices: Sequence[int]) -> Batch:
        """A padded batch: states [B, T, N_max, 4], mask [B, T, N_max] and, with pairs, pair_kind [B, E_max]
        (E_max = N_max (N_max - 1), sender-major)."""
        idx = torch.as_tensor(indices, dtype=torch.long)
        start, count = self.offsets[idx], self.num_agents[idx]
        n_max = max(int(count.max()), 1) if len(idx) else 1
        slot = torch.arange(n_max)
        valid = slot[None, :] < count[:, None]  # [B, N_max]
        # Padded slots read row 0 (any in-range row) and are zeroed below, so one gather serves the batch.
        rows = torch.where(valid, start[:, None] + slot[None, :], 0)
        states = self.states[rows] * valid[:, :, None, None].to(self.states.dtype)  # [B, N, T, 4]
        mask = self.mask[rows] & valid[:, :, None]  # [B, N, T]
        batch: Batch = {"states": states.transpose(1, 2).contiguous(), "mask": mask.transpose(1, 2).contiguous(),
                        "everyone": bool(mask.all())}  # on the host, before the batch moves to a device
        if self.pairs is not None:
            batch["pair_kind"] = pair_kind_matrix(**self.pairs, windows=idx, n=n_max)
        if self.sources is not None or self.agent_ids is not None:
            source = select_sources(self.sources, idx) or {}
            if self.agent_ids is not None:
                source["agent"] = torch.where(valid, self.agent_ids[rows], -1)
            batch["source"] = source
        return batch


def pad_collate(items: Batch | list[Batch]) -> Batch:
    """collate_fn for variable agent counts: passes a batch made by ``__getitems__`` through, and pads a list
    of single clips (states [T, N_i, 4], mask [T, N_i]) to [B, T, N_max, 4] / [B, T, N_max]."""
    if isinstance(items, dict):
        return items
    # Only reached when a dataset without __getitems__ is wrapped (e.g. a Subset): not the hot path.
    states = torch.nn.utils.rnn.pad_sequence([it["states"].transpose(0, 1) for it in items], batch_first=True)
    mask = torch.nn.utils.rnn.pad_sequence([it["mask"].transpose(0, 1) for it in items], batch_first=True)
    return {"states": states.transpose(1, 2).contiguous(), "mask": mask.transpose(1, 2).contiguous()}


def ragged_rows(offsets: torch.Tensor, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows of the selected clips of a packed layout, in order, and their new offsets.

    offsets: [S+1] long, idx: [K] long -> rows [sum of the selected counts] long, new offsets [K+1] long.
    """
    counts = offsets[idx + 1] - offsets[idx]
    new_offsets = torch.zeros(len(idx) + 1, dtype=torch.long)
    new_offsets[1:] = counts.cumsum(0)
    total = int(new_offsets[-1])
    within = torch.arange(total) - torch.repeat_interleave(new_offsets[:-1], counts)
    return torch.repeat_interleave(offsets[idx], counts) + within, new_offsets


def spread_indices(n: int, cap: int | None) -> torch.Tensor:
    """``cap`` indices spread evenly over range(n) (all of them when cap is None or >= n).

    Evenly spaced rather than the first ``cap`` so a small cap still samples every recording / file part.
    """
    if cap is None or cap >= n:
        return torch.arange(n)
    return torch.linspace(0, n - 1, cap).round().long().unique()


def check_finite(name: str, array: torch.Tensor, where: torch.Tensor | None = None) -> None:
    """Raise naming ``name`` and the first bad index if any (selected) value is NaN or infinite.

    array: [...]; where: bool broadcastable to array (only those entries are checked) or None.
    """
    bad = ~torch.isfinite(array)
    if where is not None:
        bad &= where
    if bad.any():
        first = tuple(int(i) for i in torch.nonzero(bad)[0])
        value = float(array[first])
        what = "NaN" if value != value else "inf (or beyond float32's range, |x| > 3.4e38)"
        raise ValueError(f"{name}: {int(bad.sum())} NaN/inf values (first at index {first}: {what})")


class EpochOrder(RandomSampler):
    """RandomSampler's shuffle, resumable mid-epoch: each epoch's order comes from a seed drawn from the global
    generator as the epoch starts, exactly as RandomSampler draws it (the same orders, the same random stream),
    and the seed is kept (``seed``) so that a checkpoint can carry the epoch's order. :meth:`resume` makes the
    next epoch the rest of an interrupted one: its order from the recorded seed, from the batch after the last one
    done, and the global torch random state put back to the checkpoint's as it starts (a new loader iterator draws
    a worker seed from it, which the interrupted epoch had drawn before the checkpoint)."""

    def __init__(self, data: Dataset, batch_size: int) -> None:
        super().__init__(data)
        self.batch_size = batch_size
        self.seed: int | None = None
        self._resume: tuple[int, int, torch.Tensor] | None = None

    def resume(self, seed: int, batches_done: int, rng: torch.Tensor) -> None:
        self._resume = (int(seed), int(batches_done), rng)

    def __iter__(self) -> Iterator[int]:
        if self._resume is not None:
            (self.seed, done, rng), self._resume = self._resume, None
            torch.set_rng_state(rng)
        else:
            self.seed, done = int(torch.empty((), dtype=torch.int64).random_().item()), 0
        generator = torch.Generator()
        generator.manual_seed(self.seed)
        yield from torch.randperm(len(self.data_source), generator=generator).tolist()[done * self.batch_size:]


class BaseDataModule(L.LightningDataModule):
    """The loaders API and the arguments every data module shares.

    Every subclass takes ``loader`` (the DataLoaders' settings, :class:`~dider.data.loader.Loader`: a mapping
    that overrides its class's ``LOADER`` defaults key by key; the YAML of a data set sets its own),
    ``num_train`` / ``num_val`` / ``num_test`` and ``cache_dir``, with defaults of its own. Its ``__init__`` checks
    its arguments by its class's ``SETTINGS`` (``check_settings(self, locals(), key="data")``: errors name
    ``data.<key>``), calls ``self.save_hyperparameters(logger=False)`` itself (Lightning records the arguments of
    the ``__init__`` that calls it, so hparams, and the checkpoints, hold every argument of the subclass) and then
    :meth:`init_shared`. Subclasses fill ``self.datasets`` and ``self.normalizer`` in ``setup``. The forecast
    protocol (burn-in, horizons) is the model's: it checks the clips against it (:meth:`clip_steps`); a data
    config picks the protocol that suits its clips in its defaults list: ``- /protocol@_global_.protocol: NAME``
    (``conf/protocol``).

    num_train, num_val, num_test: a cap on each split's clips (windows), evenly spread; null: all (the synthetic
    data set generates that many).
    cache_dir: where generated or preprocessed data are cached; null: $DIDER_CACHE or ~/.cache/dider (a data set
    that caches nothing takes it for a uniform interface).
    """

    # The rules of the shared arguments; a subclass adds its own (``BaseDataModule.SETTINGS | {...}``).
    SETTINGS: ClassVar[dict[str, Rule | type | ClassNode]] = {
        "loader": Loader, "num_train": optional(integer(1)), "num_val": optional(integer(1)),
        "cache_dir": optional(text),
        "num_test": optional(integer(1)),
    }
    LOADER = Loader()  # this data set's loader defaults

    collate_fn = staticmethod(pad_collate)  # passes the batches the data sets' __getitems__ make through
    units: str | None = None  # the positions' unit ("m", "ft"), for scale bars; None: unknown
    predicts = False  # True: setup("predict") builds every clip of the input (mode=predict, dider.load)

    def __init__(self) -> None:
        super().__init__()
        self.normalizer: Normalizer | None = None
        self.datasets: dict[str, Dataset] = {}
        self.source_names: dict[str, list[str]] = {}
        self.frame_step = 1  # input frames per step (downsampling readers change it)
        self.train_order: EpochOrder | None = None  # the training loader's sampler, once it is built
        # (seed, batches done, torch random state) of an epoch a checkpoint stopped in: the next training loader
        # replays the rest of it (:class:`EpochOrder`)
        self.resume_position: tuple[int, int, torch.Tensor] | None = None

    # The normaliser travels in checkpoints (Lightning stores a data module's state_dict), so a trained
    # model can normalise new data the way it was trained.
    def state_dict(self) -> dict[str, object]:
        if self.normalizer is None:
            return {}
        return {"normalizer": self.normalizer.state_dict(), "features": list(FEATURES)}

    def load_state_dict(self, state: dict[str, object]) -> None:
        """Keeps a normaliser already fitted in ``setup`` (a resumed run fits the same one); otherwise takes
        the checkpoint's."""
        if self.normalizer is None and "normalizer" in state:
            self.normalizer = Normalizer(**state["normalizer"])

    def to_device(self, device: torch.device) -> None:
        """Hold the in-memory clips on ``device`` (the model's GPU), so batches are made there; clips padded per
        batch (:class:`PackedClipDataset`) stay on the host. Loaders made afterwards take no worker processes (a
        worker cannot gather on the GPU) and no pinned memory."""
        moved = [split for split, ds in self.datasets.items() if isinstance(ds, ClipDataset)]
        for split in moved:
            self.datasets[split] = self.datasets[split].to(device)
        if moved:
            self.loader = replace(self.loader, num_workers=0, pin_memory=False)

    def use_normalizer(self, normalizer: Normalizer) -> None:
        """Normalise with a trained model's normaliser instead of fitting one (before ``setup``: prediction, and
        ``mode=eval``, which reads its clips as the checkpoint was trained to)."""
        self.normalizer = normalizer

    def train_normalizer(self, fit: Callable[[], Normalizer]) -> Normalizer:
        """The splits' normaliser in ``setup``: the one given by :meth:`use_normalizer`, else ``fit()``'s (on the
        train split)."""
        return self.normalizer if self.normalizer is not None else fit()

    def init_shared(self) -> None:
        """Set ``loader`` and ``cache_dir`` from ``self.hparams``."""
        h = self.hparams
        self.loader = replace(self.LOADER, **dict(h.loader or {}))
        self.cache_dir = Path(h.cache_dir) if h.cache_dir else default_cache_dir()

    def clip_steps(self) -> dict[str, int]:
        """Each built split's clip length in steps (after ``setup``), which the forecast protocol must fit."""
        return {split: int(ds.states.shape[1]) for split, ds in self.datasets.items()}

    def largest_edge_label(self) -> dict[str, int]:
        """Each built split's largest ground-truth edge type (after ``setup``), for the splits that have labels."""
        labelled = {split: getattr(ds, "edges", None) for split, ds in self.datasets.items()}
        return {split: int(e.max()) for split, e in labelled.items() if e is not None and e.numel()}

    def background(self, split: str, index: int) -> tuple[object, tuple[float, float, float, float]] | None:
        """An image to draw clip ``index`` of ``split`` on, with its extent in the data's raw units (for
        ``imshow``), or None (the default: no scene image)."""
        return None

    def _dataloader(self, split: str, train: bool) -> DataLoader:
        if split not in self.datasets:
            raise RuntimeError(f"{type(self).__name__}: call setup() before asking for the {split} loader")
        batch_size = self.loader.batch_size if train else self.loader.eval_batch_size
        order: dict[str, Any] = {"shuffle": False}
        if train:  # no ``shuffle`` given: Lightning tells a shuffled loader by its RandomSampler (DDP replaces it)
            self.train_order = EpochOrder(self.datasets[split], batch_size)
            if self.resume_position is not None:
                self.train_order.resume(*self.resume_position)
                self.resume_position = None
            order = {"sampler": self.train_order}
        elif dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
            # DDP evaluation: each clip exactly once (Lightning's default sampler pads the shards by
            # repeating clips, which the metrics would count twice); rank r holds clips r, r + W, ...
            order["sampler"] = UnrepeatedDistributedSampler(self.datasets[split], shuffle=False)
        return DataLoader(
            self.datasets[split],
            batch_size=batch_size,
            **order,
            drop_last=False,
            num_workers=self.loader.num_workers,
            pin_memory=self.loader.pin_memory,
            persistent_workers=self.loader.num_workers > 0,
            collate_fn=self.collate_fn,
        )

    def train_dataloader(self) -> DataLoader:
        return self._dataloader("train", train=True)

    def val_dataloader(self) -> DataLoader:
        return self._dataloader("val", train=False)

    def test_dataloader(self) -> DataLoader:
        return self._dataloader("test", train=False)

    def predict_dataloader(self) -> DataLoader:
        """Every clip of the input, in order (``setup("predict")`` builds it, normalised with the normaliser
        given to :meth:`use_normalizer`)."""
        return self._dataloader("predict", train=False)

    def predict_normalizer(self, where: str) -> Normalizer:
        """The normaliser a ``predict`` setup must use: a trained model's, never one fitted on the new data."""
        if self.normalizer is None:
            raise ValueError(f"{where}: prediction normalises with the trained model's normaliser; call "
                             f"use_normalizer(...) first (dider.load and mode=predict do)")
        return self.normalizer
