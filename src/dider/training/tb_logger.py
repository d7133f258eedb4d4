"""TensorBoard as a run's dashboard: curves for what changes during training, results where results
are read."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from lightning.pytorch.loggers import TensorBoardLogger as LightningTensorBoardLogger

RESULTS = "~results/"


class TensorBoardLogger(LightningTensorBoardLogger):
    """Lightning's TensorBoard logger without the scalars that read as noise on the dashboard: the
    ``epoch`` scalar Lightning adds to every log call (its card opened the scalars tab), and the
    test pass's ``test/*`` values, which are one point each at the last step. The test results are
    written once, with the HParams entry at the end of a run (:meth:`log_hyperparams` with metrics,
    which the app calls), and in full in the run's results card (the text tab) and ``metrics.json``.
    The HParams tab reads its metrics from scalars, so they are written under :data:`RESULTS`
    (``test/ade/h20`` as ``~results/ade/h20``): TensorBoard orders the scalar groups by name, opens
    the first two, and ``~`` sorts after ``train/`` and ``val/``, so the tab opens on the training
    curves and the one-point results sit closed at the end."""

    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        keep = {k: v for k, v in metrics.items() if k != "epoch" and not k.startswith("test/")}
        if keep:
            super().log_metrics(keep, step)

    def log_hyperparams(self, params: Any, metrics: Mapping[str, Any] | None = None,
                        step: int | None = None) -> None:
        # Lightning writes them through log_metrics, which lets these names through
        if metrics is not None:
            metrics = {RESULTS + k.removeprefix("test/") if k.startswith("test/") else k: v
                       for k, v in metrics.items()}
        super().log_hyperparams(params, metrics, step)
