"""A data module of clips built as its data config builds it, without composing the whole app's config, and nested
settings merged key by key (:func:`merged`) for the tests that build a module of long tracks themselves."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from dider.data.clips import ClipsDataModule
from dider.targets import builtin_classes

CONF = Path(__file__).resolve().parents[2] / "conf" / "data"


def data_module(name: str, **settings: Any) -> ClipsDataModule:
    """The module of ``conf/data/NAME.yaml`` (a data set of clips: ``synth``, ``springs``, ``basketball``, ...): the
    YAML's own values (sizes, loader), the class its source's schema names (``_target_``), and ``settings``
    (nested as the YAML nests them: the source's under ``source``) over them key by key. The settings reach the
    module as a config gives them (tuples as lists) but not through OmegaConf, so that a test may hand it values no
    config file could hold (a NumPy integer)."""
    body = OmegaConf.load(CONF / f"{name}.yaml")
    defaults = OmegaConf.to_container(body.pop("defaults"))
    schema = next(d["/schema@source"] for d in defaults if isinstance(d, dict) and "/schema@source" in d)
    target = next(path for path, cls in builtin_classes("clip source").items() if cls.__name__ == schema)
    yaml = OmegaConf.to_container(OmegaConf.merge({"source": {"_target_": target}}, body), resolve=True)
    return ClipsDataModule(**merged(yaml, listed(settings)))


def merged(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``over`` on ``base``, nodes (mappings) merged key by key as OmegaConf merges a config's."""
    out = dict(base)
    for key, value in over.items():
        both = isinstance(value, Mapping) and isinstance(out.get(key), Mapping)
        out[key] = merged(out[key], value) if both else value
    return out


def listed(value: Any) -> Any:
    """``value`` with its tuples as lists, in its nodes too (as a config holds a sequence)."""
    if isinstance(value, Mapping):
        return {k: listed(v) for k, v in value.items()}
    return [listed(v) for v in value] if isinstance(value, (list, tuple)) else value
