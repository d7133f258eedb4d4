"""A data module built from flat settings (as older configs wrote them), nested as today's config nests them."""

from __future__ import annotations

from typing import Any

from dider.data.legacy import nest_args


def flat(cls: type, **settings: Any) -> Any:
    """``cls`` built from ``settings`` given flat: the source's under ``data.source``, the cut's under ``windows``."""
    return cls(**nest_args(f"{cls.__module__}.{cls.__qualname__}", settings)[1])
