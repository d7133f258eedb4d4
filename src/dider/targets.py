"""Building the classes a config names (``_target_`` nodes), by one rule for a run's own config and for a file's.

A checkpoint, a shipped model or a run folder's recorded config is data: loading it must never call code the user
did not choose. So a node is checked whole before anything is imported or called, and built here, not by Hydra:

- a ``_target_`` is a *class of the kind its key expects*: a network at ``net``, an encoder at ``net.encoder``, a
  prior, duration or decoder plugin at theirs, the objective at ``net.objective`` and a term under it, an optimiser or
  a learning-rate scheduler at ``optimizer`` / ``scheduler`` (the only nodes that may be ``_partial_``), a data
  module at ``data`` and its source at ``data.source`` (a clip source or a track source, the kind its data module's
  class reads: ``SOURCE_KIND``). A ``_target_`` anywhere else, a function, ``_args_`` or any other ``_``-key is
  refused;
- the classes a key accepts are dider's own for that kind (:func:`builtin_classes`) and the classes the user trusts
  (``trust``: dotted class paths). A run's own config (the command line and the user's config files) is the user's
  choice, so everything it names is trusted; what a file names is trusted only where the user says so:
  ``dider.load(path, trust=["mypkg.MyEncoder"])``, or ``trust=[mypkg.MyEncoder]`` on the command line of
  ``mode=eval`` / ``mode=predict`` (whose own ``model`` config's targets count as named by the user too);
- every other value is plain data (strings, numbers, booleans, None, lists and string-keyed dicts), handed to the
  class as it is: no interpolation, no conversion.

A refusal names the file, the key path and the target (:class:`Untrusted`). A module prefix is not the rule: a
prefix lets any function of an allowed module through (a writer, then a loader that unpickles).
"""

from __future__ import annotations

import functools
import importlib
import inspect
from collections.abc import Collection, Iterator, Mapping
from pathlib import Path
from typing import Any

# The kind of the node under each key of its parent's kind ("*": every key). Keys not listed hold plain data.
# "module" is the LightningModule's settings (a checkpoint's hyper-parameters), a node without a class. SOURCE: the
# kind that the data module's class reads (its ``SOURCE_KIND``; none: plain data), as a clips module reads clip
# sources and a tracks module track sources.
SOURCE = "the data module's source"
CHILDREN: dict[str, dict[str, str]] = {
    "module": {"net": "network", "optimizer": "optimizer", "scheduler": "scheduler"},
    "network": {"encoder": "encoder", "prior": "prior", "duration": "duration", "decoder": "decoder",
                "objective": "objective"},
    "objective": {"*": "term"},
    "data": {"source": SOURCE},
}
PARTIAL_KINDS = ("optimizer", "scheduler")  # factories the module completes with its parameters
PLAIN = (str, int, float, bool, type(None))


class Untrusted(ValueError):
    """A config node that would build something a loaded file may not: names the file, the key and the target."""


def build(node: Mapping[str, Any], kind: str, where: str | Path, path: str = "",
          trust: Collection[str] = ()) -> Any:
    """The object a ``_target_`` node of ``kind`` describes, its children built first; checked whole by
    :func:`check` before any import or call. ``where``: the file (or config) the node comes from, ``path`` its key
    path there; ``trust``: dotted class paths the user trusts beside dider's own."""
    node = _container(node)
    check(node, kind, where, path, trust)
    return _make(node, kind, path, where)


def check(node: Any, kind: str, where: str | Path, path: str = "", trust: Collection[str] = ()) -> None:
    """Raise :class:`Untrusted` unless every ``_target_`` in ``node`` is a class of the kind its key expects, dider's
    own or trusted, and every other value is plain data. Imports nothing that is not already imported, calls
    nothing but the import of a trusted class's module."""
    trusted, node = frozenset(trust), _container(node)
    if not isinstance(node, Mapping) or (kind != "module" and "_target_" not in node):
        raise Untrusted(f"{where}: {path or 'the node'} is not a config node with a _target_ (expected a "
                        f"{kind} class)")
    for key_path, value, expected in _walk(node, kind, path, where):
        if expected == "module":  # the LightningModule's settings: no class of their own, their children checked
            if "_target_" in value:
                raise Untrusted(f"{where}: {key_path or 'the model config'}._target_={value['_target_']!r}: the "
                                f"model config's top holds settings, not a class")
            continue
        if expected is None:  # plain data
            if isinstance(value, Mapping) and "_target_" in value:
                raise Untrusted(f"{where}: {key_path}._target_={value['_target_']!r}: no class is built there "
                                f"(a file's config may build classes only where a plugin, term, optimiser, data "
                                f"module or its source goes)")
            if not isinstance(value, (*PLAIN, list, tuple, Mapping)):
                raise Untrusted(f"{where}: {key_path}: a {type(value).__name__}, not plain data")
            if isinstance(value, Mapping) and (bad := [k for k in value if not isinstance(k, str)]):
                raise Untrusted(f"{where}: {key_path}: key {bad[0]!r} is not a string")
            continue
        target = value.get("_target_")
        here = f"{key_path}._target_" if key_path else "_target_"
        if target is None:
            raise Untrusted(f"{where}: {here}: not set (a {expected} class's dotted path)")
        if not isinstance(target, str):
            raise Untrusted(f"{where}: {here}={target!r}: not a class path")
        if target not in builtin_classes(expected) and target not in trusted:
            raise Untrusted(f"{where}: {here}={target!r}: not one of dider's {expected} classes "
                            f"({', '.join(sorted(builtin_classes(expected)))}); a class of your own is built only if "
                            f"you trust it: dider.load(path, trust=[{target!r}]), or trust=[{target}] on the command "
                            f"line")
        for special in (k for k in value if isinstance(k, str) and k.startswith("_") and k != "_target_"):
            if special == "_partial_" and expected in PARTIAL_KINDS and value[special] is True:
                continue
            raise Untrusted(f"{where}: {key_path}.{special} (beside _target_={target!r}): refused; a file's config "
                            f"passes its settings by name, as plain values")


def _container(node: Any) -> Any:
    """An OmegaConf node as plain containers, resolved (a run's own config); anything else as it is."""
    from omegaconf import DictConfig, OmegaConf

    return OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else node


def _walk(node: Mapping[str, Any], kind: str, path: str, where: str | Path) -> Iterator[tuple[str, Any, str | None]]:
    """(key path, value, expected kind or None for plain data) for the node itself and everything below it. The
    node comes first: its own target is checked before its children's kinds are looked up (a data module's class
    says its source's)."""
    yield path, node, kind
    for key, value in node.items():
        sub = f"{path}.{key}" if path else str(key)
        if key == "_target_":
            continue
        child = _child_kind(node, kind, key, path, where) if isinstance(key, str) and not key.startswith("_") else None
        if child is not None and isinstance(value, Mapping):
            yield from _walk(value, child, sub, where)
        elif child is not None and value is None:
            continue  # a term (or scheduler) left out
        else:
            yield from _in_data(value, sub)


def _in_data(value: Any, path: str) -> Iterator[tuple[str, Any, None]]:
    yield path, value, None
    if isinstance(value, Mapping):
        for key, sub in value.items():
            yield from _in_data(sub, f"{path}.{key}")
    elif isinstance(value, (list, tuple)):
        for i, sub in enumerate(value):
            yield from _in_data(sub, f"{path}[{i}]")


def _child_kind(node: Mapping[str, Any], kind: str, key: str, path: str, where: str | Path) -> str | None:
    """The kind of the node under ``key`` of a node of ``kind`` (whose target is checked already), or None: data."""
    children = CHILDREN.get(kind, {})
    child = children.get(key, children.get("*"))
    if child == SOURCE:  # the data module's class says which sources it reads; resolving it imports a trusted class
        return getattr(resolve(node["_target_"], kind, path, where), "SOURCE_KIND", None)
    return child


def _make(node: Mapping[str, Any], kind: str, path: str, where: str | Path) -> Any:
    """Build a checked node: children first, then its class with the settings by name."""
    kwargs: dict[str, Any] = {}
    for key, value in node.items():
        if key.startswith("_"):
            continue
        child = _child_kind(node, kind, key, path, where)
        sub = f"{path}.{key}" if path else key
        kwargs[key] = _make(value, child, sub, where) if child and isinstance(value, Mapping) else plain(value)
    cls = resolve(node["_target_"], kind, path, where)
    return functools.partial(cls, **kwargs) if node.get("_partial_") is True else cls(**kwargs)


def plain(value: Any) -> Any:
    """A plain copy of ``value``: mappings as dicts, tuples and lists as lists, all the way down (what a YAML file
    would hold; a class built from it never shares the file's lists)."""
    if isinstance(value, Mapping):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return value


def resolve(target: str, kind: str, path: str = "", where: str | Path = "") -> type:
    """The class ``target`` names: dider's own of ``kind``, else imported (a trusted path) and checked to be a class
    of that kind; a refusal names ``where`` (the file) and ``path`` (the key)."""
    if (cls := builtin_classes(kind).get(target)) is not None:
        return cls
    module_name, _, name = target.rpartition(".")
    here = f"{where}: " if where else ""
    try:
        found: Any = getattr(importlib.import_module(module_name), name)
    except (ImportError, AttributeError, ValueError):
        raise Untrusted(f"{here}{path}._target_={target!r}: no such class (module {module_name!r} has no "
                        f"{name!r})") from None
    if not inspect.isclass(found):
        raise Untrusted(f"{here}{path}._target_={target!r}: a {type(found).__name__}, not a class; only classes are "
                        f"built")
    if problem := kind_problem(found, kind):
        raise Untrusted(f"{here}{path}._target_={target!r}: {problem}")
    return found


def kind_problem(cls: type, kind: str) -> str | None:
    """Why ``cls`` cannot go where a ``kind`` goes, else None: a subclass of the kind's base class, or (a plugin
    seam, a structural type) a class with the seam's methods."""
    interface = _interfaces()[kind]
    if getattr(interface, "_is_protocol", False):
        methods = [n for n, v in vars(interface).items() if callable(v) and (not n.startswith("_") or n == "__call__")]
        missing = sorted(n for n in methods if not callable(getattr(cls, n, None)))
        seam = kind if kind.endswith("source") else f"{kind} plugin"
        return f"not a {seam} (missing {missing})" if missing else None
    return None if issubclass(cls, interface) else f"not a {kind} class (a {interface.__name__})"


def class_path(cls: type) -> str:
    """The dotted path a ``_target_`` names ``cls`` by (what a data module records of its source)."""
    return f"{cls.__module__}.{cls.__qualname__}"


# Each kind's base class or plugin seam, and dider's own classes of it, by dotted path: this module sits below the
# models and data (they build through it), so it names them, and reads them at first use.
INTERFACES = {"network": "dider.models.vae.RelationalVAE", "encoder": "dider.models.plugins.Encoder",
              "prior": "dider.models.plugins.Prior", "duration": "dider.models.plugins.Duration",
              "decoder": "dider.models.plugins.Decoder", "objective": "dider.models.objective.Objective",
              "term": "dider.models.objective.Term", "optimizer": "torch.optim.Optimizer",
              "scheduler": "torch.optim.lr_scheduler.LRScheduler", "data": "lightning.LightningDataModule",
              "clip source": "dider.data.clip_source.ClipSource", "track source": "dider.data.tracks.TrackSource"}
BUILTIN = {
    "network": ("dider.models.vae.RelationalVAE",),
    "encoder": ("dider.models.encoder.GNNLSTMEncoder",),
    "prior": ("dider.models.prior.LearnedPrior", "dider.models.prior.FixedPrior"),
    "duration": ("dider.models.durations.PerStepDuration", "dider.models.durations.StaticDuration",
                 "dider.models.durations.LearnedDuration", "dider.models.segment_end.SegmentEnd",
                 "dider.models.gate.HoldGate"),
    "decoder": ("dider.models.decoders.MarkovDecoder", "dider.models.decoders.RecurrentDecoder",
                "dider.models.baselines.ConstantVelocity"),
    "objective": ("dider.models.objective.Objective",),
    "term": tuple(f"dider.models.{m}" for m in ("likelihood.GaussianNLL", "objective.EdgeKL", "objective.DurationKL",
                                                "objective.Sparsity", "objective.Indifference", "objective.PriorFit",
                                                "objective.BoundaryFit")),
    "data": ("dider.data.clips.ClipsDataModule", "dider.data.tracks.TracksDataModule"),
    # the sources: the one list of dider's (the config schemas are made from these classes)
    "clip source": ("dider.data.simulators.push.Push", "dider.data.simulators.particles.Simulation",
                    *(f"dider.data.readers.{m}" for m in ("nri_files.NRIFiles", "dnri_files.DNRIFiles",
                                                          "basketball.BasketballFiles", "trajectories.NpzFile"))),
    "track source": ("dider.data.track_sources.TableFile", "dider.data.readers.eth_ucy.EthUcyFiles",
                     "dider.data.track_sources.KloppySource", "dider.data.levelx.source.LevelXSource"),
}


def _named(path: str) -> Any:
    module, _, name = path.rpartition(".")
    return getattr(importlib.import_module(module), name)


@functools.cache
def _interfaces() -> dict[str, type]:
    return {kind: _named(path) for kind, path in INTERFACES.items()}


@functools.cache
def builtin_classes(kind: str) -> dict[str, type]:
    """dider's classes of ``kind`` by dotted path (and torch's optimisers and schedulers, by their public paths)."""
    if kind in ("optimizer", "scheduler"):
        import torch

        space, base = (torch.optim, torch.optim.Optimizer) if kind == "optimizer" else (
            torch.optim.lr_scheduler, torch.optim.lr_scheduler.LRScheduler)
        return {f"{space.__name__}.{n}": c for n, c in vars(space).items()
                if inspect.isclass(c) and issubclass(c, base) and c is not base}
    return {path: _named(path) for path in BUILTIN.get(kind, ())}


def named_targets(node: Any) -> set[str]:
    """Every ``_target_`` string in a (plain) config node: what a run's own config names, and so trusts."""
    found: set[str] = set()
    if isinstance(node, Mapping):
        if isinstance(target := node.get("_target_"), str):
            found.add(target)
        for value in node.values():
            found |= named_targets(value)
    elif isinstance(node, (list, tuple)):
        for value in node:
            found |= named_targets(value)
    return found
