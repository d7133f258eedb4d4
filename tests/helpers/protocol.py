"""The forecast protocol's check of a data module's clips, as a training run makes it (its callback's ``setup``),
without a trainer: ``fits(dm, burn_in, horizons)``."""

from __future__ import annotations

from collections.abc import Sequence
from types import SimpleNamespace

import lightning as L

from dider.training.callbacks import ProtocolFits


def fits(dm: L.LightningDataModule, burn_in: int, horizons: Sequence[int], stage: str = "test") -> None:
    """Raise as a run would at ``stage`` when the protocol's ``burn_in`` and ``horizons`` do not fit the clips."""
    model = SimpleNamespace(protocol=SimpleNamespace(burn_in=burn_in, horizons=list(horizons)))
    ProtocolFits().setup(SimpleNamespace(datamodule=dm), model, stage)  # type: ignore[arg-type]
