"""Each plugin's settings written once, in its constructor: the config schema of a plugin class is made from its
signature (every argument, with the signature's default) and registered in Hydra's ConfigStore as
``schema/<Class>`` when the config package ``dider.conf`` is imported. A plugin's YAML starts from it
(``defaults: [/schema@_here_: <Class>, _self_]``) and writes only what differs: an interpolation, a measured
choice, the variant's own value. Composition refuses a key the class does not take, also where an experiment
file sets it, and shows every setting (``python -m dider.run --cfg job``); the fields are untyped, so a value of
the wrong type reaches the class's ``SETTINGS`` and the preflight names it by its key.
"""

from __future__ import annotations

import dataclasses
import inspect
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from dider.models.decoders import MarkovDecoder, RecurrentDecoder
from dider.models.durations import LearnedDuration, PerStepDuration, StaticDuration
from dider.models.encoder import GNNLSTMEncoder
from dider.models.gate import HoldGate
from dider.models.prior import FixedPrior, LearnedPrior
from dider.models.segment_end import SegmentEnd

# The classes the plugin groups of conf/model/net build.
PLUGINS = (GNNLSTMEncoder, LearnedPrior, FixedPrior, PerStepDuration, StaticDuration, LearnedDuration, SegmentEnd,
           HoldGate, MarkovDecoder, RecurrentDecoder)


def schema(cls: type) -> type:
    """A dataclass of ``cls``'s constructor arguments (defaults as in its signature, ``???`` where it has none)
    and its ``_target_``."""
    fields: list[tuple[str, Any, Any]] = [("_target_", str, dataclasses.field(default=f"{cls.__module__}."
                                                                                      f"{cls.__qualname__}"))]
    for name, p in inspect.signature(cls.__init__).parameters.items():
        if name == "self" or p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            continue
        if p.default is p.empty:
            fields.append((name, Any, dataclasses.field(default=MISSING)))
        elif isinstance(p.default, (list, tuple, dict)):  # a mutable default: one copy per config
            fields.append((name, Any, dataclasses.field(default_factory=lambda d=p.default: _plain(d))))
        else:
            fields.append((name, Any, dataclasses.field(default=p.default)))
    return dataclasses.make_dataclass(f"{cls.__name__}Schema", fields)


def _plain(value: Any) -> Any:
    return dict(value) if isinstance(value, dict) else list(value)


def register_schemas() -> None:
    """Store the schema of every plugin class as ``schema/<Class>``."""
    store = ConfigStore.instance()
    for cls in PLUGINS:
        store.store(group="schema", name=cls.__name__, node=schema(cls))
