"""Parameter-keyed on-disk caches: a file name carries a hash of everything that made its content, and
files are written atomically (:mod:`dider.io`), so a killed process never leaves a half-written one."""

from __future__ import annotations

import hashlib
import json
from typing import Any


def cache_key(params: dict[str, Any]) -> str:
    """A short stable hash of JSON-serialisable parameters."""
    blob = json.dumps(params, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]
