"""A run folder's lock (``.dider.lock``): one live run writes a folder at a time; the lock of a run
that is gone (its process ended, or its pid since given to another process) is taken over, one that
cannot be says which file it is, who holds it and how to proceed."""

from __future__ import annotations

import json
import logging
import os
import socket
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from dider.training.runfolder import RunRefused, is_rank_zero
from dider.validation import ConfigError

log = logging.getLogger(__name__)

LOCK = ".dider.lock"
HELD: set[Path] = set()  # the locks this process holds


class RunLock:
    """``folder/.dider.lock`` while a run writes the folder; a second live run there fails naming
    the first."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / LOCK
        self.held = False

    def __enter__(self) -> RunLock:
        if not is_rank_zero():
            return self
        self.path.parent.mkdir(parents=True, exist_ok=True)
        me = {"pid": os.getpid(), "host": socket.gethostname(), "started": _started(os.getpid())}
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                owner = self._owner()
                if owner is not None and _alive(owner, self.path):
                    raise RunRefused(
                        f"{self.path.parent} is being written by another run (pid "
                        f"{owner.get('pid')} on {owner.get('host')}, its lock {self.path}); wait "
                        "for it, or use another hydra.run.dir. If that run is gone (another "
                        f"machine's, or a container since restarted), remove {self.path} and run "
                        "again") from None
                log.warning("%s: taking over the lock of a run that is gone (%s)", self.path, owner)
                self.path.unlink(missing_ok=True)
                continue
            try:
                with os.fdopen(fd, "w") as f:
                    json.dump(me, f)
            except OSError as e:  # a full disk: no empty lock left behind, and the file named
                self.path.unlink(missing_ok=True)
                raise OSError(e.errno, f"{self.path}: could not write the run folder's lock "
                                       f"({e.strerror})") from e
            self.held = True
            HELD.add(self.path.resolve())
            return self
        raise ConfigError(f"{self.path}: could not take the run folder's lock")

    def _owner(self) -> dict[str, Any] | None:
        try:
            return json.loads(self.path.read_text())
        except (OSError, ValueError):
            return None

    def __exit__(self, *exc: object) -> None:
        if self.held:
            HELD.discard(self.path.resolve())
            self.path.unlink(missing_ok=True)
            self.held = False


def owner_of(folder: Path) -> dict[str, Any] | None:
    """The live run that holds ``folder``'s lock (its pid and host), or None (no lock, or its writer
    is gone)."""
    try:
        owner = json.loads((folder / LOCK).read_text())
    except (OSError, ValueError):
        return None
    return owner if isinstance(owner, dict) and _alive(owner, folder / LOCK) else None


def _started(pid: int) -> int | None:
    """When process ``pid`` started (clock ticks since boot, Linux's /proc), or None where that
    cannot be read: with the pid it names one process, not whichever later process was given the
    same number."""
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19])
    except (OSError, ValueError, IndexError):
        return None


def _alive(owner: Mapping[str, Any], lock: Path) -> bool:
    """Whether the writer of ``lock`` still runs. This very process is it only while it holds the
    lock (a lock naming our pid that we do not hold is a container's restarted as the same pid); a
    pid that now names a later process (another start time) is gone."""
    if owner.get("host") != socket.gethostname():
        # another machine's process: cannot tell, so respect it (the refusal says how to proceed)
        return True
    try:
        pid = int(owner["pid"])
        if pid == os.getpid():
            return lock.resolve() in HELD
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, ValueError, KeyError, TypeError):
        return True
    started = owner.get("started")
    return started is None or _started(pid) in (None, started)
