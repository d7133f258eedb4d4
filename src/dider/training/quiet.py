"""Library messages that say nothing about a run, silenced where they come from, so a run's output
is its own: Lightning's tips about its cloud products and notes on its own bookkeeping, a
deprecation inside Lightning's own pytree helper, the model summary's note that it counts bf16
parameters as fp32, and the hint to add data-loader workers (the data sets here are in memory:
workers would only copy them), and the warning that a loader is not resumable mid-epoch (the
training order is: :class:`dider.training.callbacks.ResumeMidEpoch`)."""

from __future__ import annotations

import logging
import warnings

WARNINGS = (
    r".*isinstance\(treespec, LeafSpec\)` is deprecated.*",
    r".*is not supported by the model summary.*",
    r".*does not have many workers which may be a bottleneck.*",
    r".*ended before the epoch ended and your dataloader is not resumable.*",
)


# Lightning's info lines with nothing to act on: product tips, and two notes on its own bookkeeping
# at test
INFO = ("💡 Tip", "returned in `LightningModule.configure_callbacks` will override",
        "to estimate number of stepping batches")


class _NoTips(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return not any(part in message for part in INFO)


def silence_library_chatter() -> None:
    """Install the filters (idempotent)."""
    for pattern in WARNINGS:
        warnings.filterwarnings("ignore", message=pattern)
    rank_zero = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    if not any(isinstance(f, _NoTips) for f in rank_zero.filters):
        rank_zero.addFilter(_NoTips())
