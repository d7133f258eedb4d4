"""How a data module batches its clips: the data config's ``loader`` node, one set of settings for every data set."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import ClassVar

from dider.validation import Rule, boolean, check_settings, integer


@dataclass(frozen=True)
class Loader:
    """The DataLoaders' settings: a data set's defaults are in its YAML's ``loader`` node (or its module's class,
    ``LOADER``, where one module serves one data set); a config's ``loader`` node overrides them key by key."""

    batch_size: int = 16  # clips per training batch
    eval_batch_size: int = 64  # clips per validation, test and prediction batch (no gradients: larger fits)
    num_workers: int = 0  # loader processes (0: batches are made in the training process)
    pin_memory: bool = False  # page-locked batches, for faster copies to a GPU

    SETTINGS: ClassVar[dict[str, Rule]] = {"batch_size": integer(1), "eval_batch_size": integer(1),
                                           "num_workers": integer(0), "pin_memory": boolean}

    def __post_init__(self) -> None:
        check_settings(self, asdict(self), key="data.loader")
