"""Interrupted runs: SIGTERM and Ctrl-C where no Lightning loop listens for them (the figures, drawn
after the results), and the checkpoint a resumed run leaves behind."""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.utilities.exceptions import SIGTERMException

from dider.training.runfolder import is_rank_zero

log = logging.getLogger(__name__)


@contextmanager
def stop_on_signals() -> Iterator[None]:
    """Within the block, SIGTERM or SIGINT raises ``SIGTERMException`` (as inside Lightning's loops)
    instead of killing the process: the write in progress removes its temporary file
    (:func:`dider.io.atomic_write`) and the caller ends the run as an interrupted one, with a
    word."""
    # signals reach the main thread only
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum: int, frame: object) -> None:
        raise SIGTERMException

    before = {sig: signal.signal(sig, stop) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)


def drop_resumed_from(ckpt: str | None, checkpointers: list[ModelCheckpoint]) -> None:
    """Lightning never deletes the checkpoint a run resumed from: one of the folder's best-k that a
    better epoch has since displaced is removed here, as it would have been without the resume."""
    if not ckpt or not checkpointers or not Path(ckpt).is_file() or not is_rank_zero():
        return
    resumed = Path(ckpt).resolve()
    for c in checkpointers:
        kept = {Path(p).resolve() for p in [*c.best_k_models, c.last_model_path] if p}
        if c.dirpath is None or resumed.parent != Path(c.dirpath).resolve() or resumed in kept:
            return
    log.info("removing %s: the run resumed from it, and better epochs have replaced it", resumed)
    resumed.unlink()
