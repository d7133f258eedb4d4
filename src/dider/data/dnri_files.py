"""DataModule of the synthetic data files of the public DNRI code (the reader, the layout and the edges'
alignment: :mod:`dider.data.readers.dnri_files`).

Normalisation. DNRI maps positions and velocities separately to [-1, 1] with scalar min/max over every
value of ``train_feats`` (its default), or one range for all four features (``--same_data_norm``), or not
at all (``--no_data_norm``). ``normalization: separate | same | none`` does the same with our
:class:`~dider.data.batch.Normalizer` (``none`` is the identity range (-1, 1)). As in DNRI the ranges are
fitted on the whole train file, also when ``num_train`` uses fewer of its clips.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any, ClassVar

import torch

from dider.data.batch import Normalizer
from dider.data.clip_splits import capped, clip_datasets
from dider.data.common import SPLITS, ClipDataModule, source_node
from dider.data.loader import Loader
from dider.data.readers import dnri_files
from dider.validation import Rule, check_settings, one_of

log = logging.getLogger(__name__)

NORMALIZATIONS = ("separate", "same", "none")


def fit_normalizer(feats: torch.Tensor, normalization: str) -> Normalizer:
    """DNRI's normalisation of ``feats`` [S, T, N, 4] as a Normalizer (module docstring)."""
    if normalization == "none":
        return Normalizer((-1.0, 1.0), (-1.0, 1.0))  # the identity map
    if normalization == "same":
        lo, hi = feats.min().item(), feats.max().item()
        return Normalizer((lo, hi), (lo, hi))
    return Normalizer.fit(feats)


class DNRIFilesDataModule(ClipDataModule):
    """Clips of the DNRI code's synthetic files (module docstring). Batches: states [B, T, N, 4] normalised,
    mask [B, T, N] (all True), edges [B, T-1, E] long, source ``clip`` [B] (the clip's index in its file).

    After ``setup``: ``normalizer``, ``datasets`` (ClipDataset per split). ``setup("predict")`` serves every
    clip of the ``predict_split`` files, normalised with the trained model's normaliser. ``cache_dir`` is
    accepted for a uniform interface; nothing is cached.
    """

    predicts = True

    SETTINGS: ClassVar[dict[str, Rule | type]] = ClipDataModule.SETTINGS | {
        "normalization": one_of(*NORMALIZATIONS)}
    LOADER = Loader(batch_size=16, eval_batch_size=256)
    SOURCE = dnri_files.DNRIFiles()  # data.source overrides it key by key

    def __init__(
        self,
        source: Mapping[str, Any] | None = None,
        normalization: str = "separate",
        num_train: int | None = None,
        num_val: int | None = None,
        num_test: int | None = None,
        loader: Mapping[str, Any] | None = None,
        cache_dir: str | None = None,
    ) -> None:
        """source: the files (:class:`~dider.data.readers.dnri_files.DNRIFiles`): ``root``, the folder holding the
        six files (required), and ``predict_split``."""
        super().__init__()
        check_settings(self, locals(), key="data")
        self.source = source_node(self.SOURCE, source)
        self.save_hyperparameters(logger=False)
        self.hparams["source"] = asdict(self.source)  # as read
        self.init_shared()
        self.frame_step = 1

    def setup(self, stage: str | None = None) -> None:
        h, src = self.hparams, self.source
        if stage == "predict":  # every clip of one split's files, the trained model's normalisation
            if "predict" not in self.datasets:
                normalizer = self.predict_normalizer(f"data.source.root={src.root}")
                clips = dnri_files.read(src.root, (src.predict_split,))[src.predict_split]
                self.datasets["predict"] = clip_datasets({"predict": clips}, normalizer)["predict"]
            return
        if all(s in self.datasets for s in SPLITS):
            return
        raw = dnri_files.read(src.root)
        root = Path(src.root).expanduser()
        try:
            self.normalizer = self.train_normalizer(lambda: fit_normalizer(raw["train"].states, h.normalization))
        except ValueError as e:  # e.g. agents that never move: a zero velocity range
            raise ValueError(f"{root / 'train_feats'}: cannot fit the normalisation: {e}") from None
        caps = {"train": h.num_train, "val": h.num_val, "test": h.num_test}
        self.datasets.update(clip_datasets(capped(raw, caps), self.normalizer))
        train = raw["train"].states
        log.info("DNRI files %s: %s clips of %d steps, %d agents, normalisation %s", root,
                 {s: len(d) for s, d in self.datasets.items()}, train.shape[1], train.shape[2], h.normalization)
