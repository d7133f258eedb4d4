"""Each setting written once, in its class's constructor: the config schema of a class is made from its signature
(every argument, with the signature's default) and registered in Hydra's ConfigStore as ``schema/<Class>`` when
the config package ``dider.conf`` is imported. A config node starts from it (``defaults: [/schema@_here_:
<Class>, _self_]``, or ``/schema@<key>: <Class>`` for a node below) and writes only what differs: an
interpolation, a data set's value, the variant's own choice. Composition refuses a key the class does not take,
also where an experiment file sets it, and shows every setting (``python -m dider.run --cfg job``); the fields
are untyped, so a value of the wrong type reaches the class's ``SETTINGS`` and the preflight names it by its key.

A nested node's defaults (a data module's ``loader``, say) are the class's upper-case attribute named after the
argument (``LOADER``), a dataclass or a mapping, where the signature's default is None.
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Iterable, Mapping
from dataclasses import MISSING as MISSING_FIELD
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from dider.data.pairs import PairRules
from dider.models.decoders import MarkovDecoder, RecurrentDecoder
from dider.models.durations import LearnedDuration, PerStepDuration, StaticDuration
from dider.models.encoder import GNNLSTMEncoder
from dider.models.gate import HoldGate
from dider.models.likelihood import GaussianNLL
from dider.models.objective import BoundaryFit, DurationKL, EdgeKL, Indifference, PriorFit, Sparsity
from dider.models.prior import FixedPrior, LearnedPrior
from dider.models.segment_end import SegmentEnd
from dider.models.vae import RelationalVAE
from dider.settings import NODES
from dider.targets import builtin_classes, plain
from dider.training.module import RelationalVAEModule

# The classes the configs build, each stored as schema/<Class>: the network and its plugins (conf/model/net),
# the objective's terms (conf/model/net/objective: the objective itself stays open to new terms), and dider's data
# modules and sources (conf/data: ``- /schema@source: <Class>``), the classes dider.targets builds at ``data`` and
# ``data.source``. The LightningModule's is stored by register_schemas.
PLUGINS = (GNNLSTMEncoder, LearnedPrior, FixedPrior, PerStepDuration, StaticDuration, LearnedDuration, SegmentEnd,
           HoldGate, MarkovDecoder, RecurrentDecoder)
TERMS = (GaussianNLL, EdgeKL, DurationKL, Sparsity, Indifference, PriorFit, BoundaryFit)
SOURCE_KINDS = ("clip source", "track source")


def data_classes() -> tuple[type, ...]:
    """dider's data modules and sources (:func:`dider.targets.builtin_classes`)."""
    return tuple(cls for kind in ("data", *SOURCE_KINDS) for cls in builtin_classes(kind).values())


def data_nodes() -> dict[str, Any]:
    """Nodes of their own under a data set: the consistency check's rules (``- /schema@pairs: PairRules``), and each
    track source's window defaults (``- /schema@windows: <Source>Windows``), so the YAML shows every key its class
    defaults."""
    return {"PairRules": PairRules(), **{f"{cls.__name__}Windows": cls.WINDOWS
                                        for cls in builtin_classes("track source").values()}}


def schema(cls: type, exclude: Iterable[str] = (), target: bool = True,
           extra: Mapping[str, Any] | None = None) -> type:
    """A dataclass of ``cls``'s constructor arguments but ``exclude`` (defaults as in its signature, ``???`` where
    it has none), with its ``_target_`` (unless ``target`` is False) and the fields of ``extra`` (name: default)."""
    fields: list[tuple[str, Any, Any]] = []
    if target:
        fields.append(("_target_", str, dataclasses.field(default=f"{cls.__module__}.{cls.__qualname__}")))
    for name, p in inspect.signature(cls.__init__).parameters.items():
        if name == "self" or name in exclude or p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            continue
        default = MISSING if p.default is p.empty else p.default
        if dataclasses.is_dataclass(cls) and (f := cls.__dataclass_fields__[name]).default_factory is not MISSING_FIELD:
            default = f.default_factory()  # a settings node's field with a mutable default
        if default is None and hasattr(cls, name.upper()):
            default = getattr(cls, name.upper())
        fields.append((name, Any, _field(default)))
    fields += [(name, Any, _field(default)) for name, default in (extra or {}).items()]
    return dataclasses.make_dataclass(f"{cls.__name__}Schema", fields)


def _field(default: Any) -> Any:
    """A dataclass field holding ``default``; a mutable or nested one is copied, plain, for each config."""
    if dataclasses.is_dataclass(default):
        return dataclasses.field(default_factory=lambda d=default: plain(dataclasses.asdict(d)))
    if isinstance(default, (list, tuple, Mapping)):
        return dataclasses.field(default_factory=lambda d=default: plain(d))
    return dataclasses.field(default=default)


def module_schema() -> type:
    """The model config's top: the LightningModule's settings (``net`` holds the network's config, ``protocol`` the
    forecast protocol's; the keyword-only arguments are the run's, not settings), with the network's ``name`` and
    ``num_edges``, which the model's top holds so that users type ``model.num_edges`` (``net`` interpolates them)."""
    network = inspect.signature(RelationalVAE.__init__).parameters
    module = inspect.signature(RelationalVAEModule.__init__).parameters
    return schema(RelationalVAEModule, exclude=[k for k, p in module.items() if p.kind is p.KEYWORD_ONLY],
                  target=False,
                  extra={k: network[k].default for k in ("name", "num_edges")})


def register_schemas() -> None:
    """Store the schema of every class the configs build as ``schema/<Class>``."""
    store = ConfigStore.instance()
    for cls in (*PLUGINS, RelationalVAE, *TERMS, *data_classes()):
        store.store(group="schema", name=cls.__name__, node=schema(cls))
    store.store(group="schema", name=RelationalVAEModule.__name__, node=module_schema())
    for name, node in data_nodes().items():
        store.store(group="schema", name=name, node=plain(dataclasses.asdict(node)))
    for cls in NODES.values():  # the app's own nodes (protocol, eval, predict): dataclasses already
        store.store(group="schema", name=cls.__name__, node=cls)
