"""One way to validate settings: each rule is written once.

A class that a config node builds (the network, its plugins, the objective's terms, the data modules) declares its
settings' rules in ``SETTINGS``: its constructor applies them to the values it receives (:func:`check_settings`,
naming the class, ``RelationalVAE: num_edges=1: must be >= 2 (...)``, or the key, ``data.num_train=0: must be
>= 1``) and ``dider.training.preflight.validate_config`` applies them to the node before any work starts
(:func:`settings_problems`, naming the key: ``model.num_edges=1: ...``). A setting that is a node of its own
(the data's ``loader``) names its class as its rule, or a :class:`ClassNode` where the node names its own class
(a data set's ``source``, by its ``_target_``). The app's own keys (the seed, the trainer, the
LightningModule's) have theirs in :data:`RULES`, applied by :func:`require` and the preflight alike. Every
problem is listed at once.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from dider.perf import ALLOCATORS
from dider.targets import Untrusted, builtin_classes, class_path, kind_problem, resolve

Rule = Callable[[Any], "str | None"]  # a value -> what is wrong with it, or None


class ConfigError(ValueError):
    """Invalid configuration values; the message lists each one by its key."""


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _numeric(ok: Callable[[float], bool], why: str) -> Rule:
    """A rule for numbers: ``why`` unless ``ok(value)``."""

    def rule(value: Any) -> str | None:
        if not _is_number(value):
            return "must be a number"
        return None if ok(value) else why

    return rule


def at_least(low: float, note: str = "") -> Rule:
    return _numeric(lambda v: v >= low, f"must be >= {low}{note}")


def above(low: float) -> Rule:
    """A finite number > low (inf is no rate, no learning rate, no speed)."""
    greater = _numeric(lambda v: v > low, f"must be > {low}")
    return lambda v: greater(v) or (None if math.isfinite(v) else "must be finite")


def integer(low: int, note: str = "", high: int | None = None) -> Rule:
    """A whole number in [low, high] (2.5, "abc" and true are refused: they fail late and unnamed otherwise)."""

    def rule(value: Any) -> str | None:
        if not isinstance(value, numbers.Integral) or isinstance(value, bool):  # numpy's integers too
            return "must be an integer"
        if high is not None and not low <= value <= high:
            return f"must lie in [{low}, {high}]{note}"
        return None if value >= low else f"must be >= {low}{note}"

    return rule


def finite(value: Any) -> str | None:
    return None if _is_number(value) and math.isfinite(value) else "must be a finite number"


def within(low: float, high: float, what: str = "must lie in") -> Rule:
    return _numeric(lambda v: low <= v <= high, f"{what} [{low}, {high}]")


def within_open(low: float, high: float) -> Rule:
    return _numeric(lambda v: low < v < high, f"must lie in ({low}, {high})")


def optional(rule: Rule) -> Rule:
    """``rule``, or null."""
    return lambda value: None if value is None else rule(value)


def or_word(word: str, rule: Rule) -> Rule:
    """``rule``, or the string ``word``."""
    def either(value: Any) -> str | None:
        if value == word:
            return None
        why = rule(value)
        return why and f"{why} or '{word}'"

    return either


def one_of(*options: Any) -> Rule:
    def rule(value: Any) -> str | None:
        return None if value in options else f"expected one of {list(options)}"

    return rule


def boolean(value: Any) -> str | None:
    return None if isinstance(value, bool) else "expected true or false"


def text(value: Any) -> str | None:
    """A non-empty string (a name, a metric, a path)."""
    return None if isinstance(value, str) and value else "expected a non-empty string"


def texts(value: Any) -> str | None:
    """A list of non-empty strings."""
    ok = isinstance(value, Sequence) and not isinstance(value, str) and all(isinstance(v, str) and v for v in value)
    return None if ok else "expected a list of strings"


def node_or_null(value: Any) -> str | None:
    """A config node that names its class (``_target_``), or null."""
    ok = value is None or (isinstance(value, Mapping) and "_target_" in value)
    return None if ok else "expected a node with its _target_ class, or null (left out)"


def folder_name(value: Any) -> str | None:
    """A name for a folder inside another: no path separators, not '.' or '..'."""
    ok = isinstance(value, str) and value not in ("", ".", "..") and "/" not in value and "\\" not in value
    return None if ok else "expected a folder name (no path separators)"


def class_paths(value: Any) -> str | None:
    """A list of dotted class paths (``[mypkg.encoders.MyEncoder]``)."""
    ok = isinstance(value, Sequence) and not isinstance(value, str) and all(
        isinstance(v, str) and "." in v.strip(".") for v in value)
    return None if ok else "expected a list of dotted class paths, e.g. [mypkg.encoders.MyEncoder]"


FRACTION_OF_TRAINING = within(0.0, 1.0, "a fraction of training, in")
def NUM_TYPES(value: Any) -> str | None:  # noqa: N802 (a rule, named as the other rule constants)
    """Every plugin's ``num_types``, which the model config interpolates from ``model.num_edges``: named by it."""
    why = integer(2)(value)
    return None if why is None else f"{why} (model.num_edges={value!r}: type 0 'no interaction' and at least one other)"

# The settings of the app, the trainer and the LightningModule; the model's and the data's classes declare theirs
# (SETTINGS), and so do the protocol, eval and predict nodes (dider.settings).
RULES: dict[str, Rule] = {
    "compile": boolean,
    "optimized_metric": optional(text),
    "model.name": text,
    "model.eval_seed": integer(0, " (a torch seed)", 2**64 - 1),
    "model.optimizer._partial_": boolean,
    "model.scheduler._partial_": boolean,
    "model.scheduler.step_size": integer(1),
    "model.scheduler.gamma": above(0),
    "deterministic": one_of(True, False, "warn"),  # Lightning acts on a bool or "warn" alone
    "cuda_graph": one_of("auto", True, False),
    "allocator": one_of(*ALLOCATORS),
    "seed": integer(0, " (the seeds torch, numpy and Python all accept)", 2**32 - 1),
    "threads": optional(integer(1, " (null: torch's default)")),
    "trust": class_paths,
    "trainer.max_epochs": integer(-1, " (-1: no limit)"),
    "model.optimizer.lr": above(0),
    "model.check_finite": boolean,
}


def check_arguments(where: str, checks: Mapping[str, tuple[Any, Rule]]) -> None:
    """A function's arguments by name (name -> (value, rule)); raises ValueError naming ``where`` and every
    argument that fails, e.g. ``TrainedModel.forecast: burn_in=5.0: must be an integer``."""
    found = [f"{name}={value!r}: {why}" for name, (value, rule) in checks.items() if (why := rule(value)) is not None]
    if found:
        raise ValueError(f"{where}: " + "; ".join(found))


def check_settings(owner: object, values: Mapping[str, Any], related: Mapping[str, tuple[Any, Rule]] | None = None,
                   *, key: str | None = None) -> None:
    """Check a constructor's arguments (``locals()`` at its top) by the rules its class declares once
    (``SETTINGS``: name -> rule, or name -> a class with ``SETTINGS`` of its own (or a :class:`ClassNode`) for a
    nested node; arguments
    without one are left alone), and ``related`` ones whose rule depends on another argument (name -> (value,
    rule)); raises :class:`ConfigError` listing every setting that fails, named by the class
    (``RelationalVAE: num_edges=1: ...``) or, given ``key``, by the config key (``data.num_train=0: ...``). The
    preflight applies ``SETTINGS`` to the config node that builds the class (:func:`settings_problems`)."""
    prefix = f"{key}." if key else ""
    found = _problems(type(owner).SETTINGS, values, prefix)
    found += [f"{prefix}{name}={value!r}: {why}" for name, (value, rule) in (related or {}).items()
              if (why := rule(value)) is not None]
    if found:
        raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(found) if key
                          else f"{type(owner).__name__}: " + "; ".join(found))


def _problems(rules: Mapping[str, Rule | type | ClassNode], values: Mapping[str, Any], prefix: str) -> list[str]:
    """``values`` checked by ``rules`` (see :func:`check_settings`): ``"prefix+name=value: why"`` for each."""
    found = []
    for name, value in values.items():
        rule = rules.get(name)
        if isinstance(rule, type):
            found += node_problems(rule, value, f"{prefix}{name}")
        elif isinstance(rule, ClassNode):
            found += rule.problems(value, f"{prefix}{name}")
        elif rule is not None and (why := rule(value)) is not None:
            found.append(f"{prefix}{name}={value!r}: {why}")
    return found


@dataclasses.dataclass(frozen=True)
class ClassNode:
    """The rule of a nested node that names its own class (a data set's ``source``): its ``_target_`` is a class of
    ``kind`` (:mod:`dider.targets`: dider's own, or one the config's author chose) and the class's settings sit
    beside it, checked by the class's rules (``SETTINGS``). An object in the node's place (built already, by Hydra
    or a caller) is checked to be of the kind."""

    kind: str

    def problems(self, node: Any, where: str) -> list[str]:
        """The node's problems (``where``: its key); null is left to the owner (its default)."""
        if node is None:
            return []
        if not isinstance(node, Mapping):
            if isinstance(node, (str, int, float, list, tuple)):
                return [f"{where}={node!r}: expected a node with a _target_ (a {self.kind} class) and its settings"]
            why = kind_problem(type(node), self.kind)
            return [] if why is None else [f"{where}._target_={class_path(type(node))!r}: {why}"]
        if (target := node.get("_target_")) is None:
            return [f"{where}._target_: not set; name the {self.kind}'s class (dider's: "
                    f"{', '.join(sorted(builtin_classes(self.kind)))}; or a class of your own)"]
        if not isinstance(target, str):
            return [f"{where}._target_={target!r}: not a class's dotted path"]
        try:
            cls = resolve(target, self.kind, where)
        except Untrusted as e:
            return [str(e)]
        return node_problems(cls, {k: v for k, v in node.items() if k != "_target_"}, where)


def node_problems(cls: type, node: Any, where: str) -> list[str]:
    """A nested settings node (e.g. the data's ``loader``) built into ``cls``: unknown keys and its rules."""
    if node is None:
        return []
    if dataclasses.is_dataclass(cls):
        names = [f.name for f in dataclasses.fields(cls)]
    else:  # a class of a user's own may declare no rules: its constructor's arguments
        names = list(getattr(cls, "SETTINGS", None) or [k for k in inspect.signature(cls).parameters])
    if not isinstance(node, Mapping):
        return [f"{where}={node!r}: expected a mapping of {names}"]
    unknown = [f"{where}.{k}: no such setting (expected one of {names})" for k in node if k not in names]
    return unknown + _problems(getattr(cls, "SETTINGS", {}), node, f"{where}.")  # a class may have no rules


def settings_problems(node: Any, path: str) -> list[str]:
    """The settings of every config node under ``node`` (a plain container) whose ``_target_`` class declares
    ``SETTINGS``, checked by those rules: ``"path.key=value: what is wrong"`` for each that fails."""
    found: list[str] = []
    if isinstance(node, list):
        for i, item in enumerate(node):
            found += settings_problems(item, f"{path}[{i}]")
    elif isinstance(node, Mapping):
        cls = _target_class(node.get("_target_"))
        rules = getattr(cls, "SETTINGS", {})
        found += _problems(rules, node, f"{path}.") + _unknown_arguments(cls, node, path)
        for key, value in node.items():
            if key not in rules:
                found += settings_problems(value, f"{path}.{key}")
    return found


def _unknown_arguments(cls: type | None, node: Mapping[str, Any], path: str) -> list[str]:
    """The keys of a node that its class's constructor does not take (it would fail with a TypeError once built)."""
    if cls is None:
        return []
    try:
        params = inspect.signature(cls).parameters
    except (TypeError, ValueError):  # a builtin's signature: nothing to compare
        return []
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):  # its KEYWORDS rule, if any
        rule = getattr(cls, "KEYWORDS", None)
        return [] if rule is None else [f"{path}.{k}={v!r}: {why}" for k, v in node.items()
                                        if k not in params and not str(k).startswith("_") and (why := rule(v))]
    known = [k for k, p in params.items() if p.kind is not inspect.Parameter.VAR_POSITIONAL]
    return [f"{path}.{k}: no such setting of {cls.__name__} (expected some of {known})" for k in node
            if not str(k).startswith("_") and k not in params]


def _target_class(target: Any) -> type | None:
    """The class a ``_target_`` names, or None (no target, not a class, or not importable: instantiation
    reports that one)."""
    if not isinstance(target, str) or "." not in target:
        return None
    module, _, name = target.rpartition(".")
    try:
        found = getattr(importlib.import_module(module), name, None)
    except ImportError:
        return None
    return found if isinstance(found, type) else None


def problem(key: str, value: Any) -> str | None:
    """The rule of ``key`` applied to ``value``: ``"key=value: what is wrong"``, or None when it is fine."""
    why = RULES[key](value)
    return None if why is None else f"{key}={value!r}: {why}"


def require(values: Mapping[str, Any], related: Mapping[str, tuple[Any, Rule]] | None = None) -> None:
    """Check values by their full config keys (each must have a rule in :data:`RULES`), and ``related``
    ones whose rule depends on another value (key -> (value, rule)); raises :class:`ConfigError` listing
    every problem."""
    found = [p for key, value in values.items() if (p := problem(key, value)) is not None]
    for key, (value, rule) in (related or {}).items():
        if (why := rule(value)) is not None:
            found.append(f"{key}={value!r}: {why}")
    if found:
        raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(found))
