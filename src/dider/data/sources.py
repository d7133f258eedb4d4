"""What every data set's ``data.source`` node is: a class that its ``_target_`` names, of the kind its data module
reads (a clip source for :class:`~dider.data.clips.ClipsDataModule`, a track source for
:class:`~dider.data.tracks.TracksDataModule`: :mod:`dider.targets` checks and builds it for a file's config), its
settings beside it; dider's sources check their settings as they are built (:class:`SourceSettings`), and a data
module records its source as the node that builds it again (:func:`recorded_source`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar

from dider.targets import build, class_path, named_targets
from dider.validation import ClassNode, ConfigError, Rule, check_settings


class SourceSettings:
    """A source's settings (a frozen dataclass's fields) checked by its class's rules (``SETTINGS``) as it is built,
    by whichever builder builds it (Hydra for a run's own config, :mod:`dider.targets` for a file's, a caller):
    errors name ``data.source.<key>``."""

    SETTINGS: ClassVar[dict[str, Rule | type]] = {}

    def __post_init__(self) -> None:
        check_settings(self, dataclasses.asdict(self), key="data.source")


def data_source(source: Any, kind: str, default: type | None = None) -> Any:
    """A data module's ``source`` argument as the source it reads, of ``kind`` (``clip source``, ``track source``):
    an object as it is (the config's builder built it: Hydra's instantiate for a run's own config,
    :func:`dider.targets.build` for a file's), a mapping (``_target_`` and the class's settings: the caller's own
    node, so every class it names is the caller's choice) built here, None the ``default`` class's defaults.
    Problems raise naming ``data.source._target_`` or ``data.source.<key>``."""
    if source is None and default is not None:
        return default()
    if source is None:
        source = {}
    if problems := ClassNode(kind).problems(source, "data.source"):
        raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(problems))
    if not isinstance(source, Mapping):
        return source
    return build(source, kind, "data config", "data.source", trust=named_targets(source))


def recorded_source(source: Any) -> dict[str, Any]:
    """What a data module's hyper-parameters (and so its checkpoints) hold of its source: the node that builds it
    again, ``_target_`` and the settings as read."""
    settings = dataclasses.asdict(source) if dataclasses.is_dataclass(source) else dict(vars(source))
    return {"_target_": class_path(type(source)), **settings}
