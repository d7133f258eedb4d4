"""Command-line overrides that name no key of the config: answered with dider's message (the nearest keys, and the
new place of a key that 0.2 moved) before Hydra's own, which only says that the key cannot be overridden."""

from __future__ import annotations

import difflib
import re
from collections.abc import Mapping, Sequence
from typing import Any

from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

# Keys that 0.2 moved (a message, not a reading of the old layout): a data source's settings went under
# data.source, the cut's under data.windows, the forecast protocol to protocol.
SOURCE_KEYS = ("path", "root", "columns", "frame_rate", "num_steps", "push_factor", "push", "provider",
               "files", "options", "ball", "recordings", "classes", "background_scale", "format", "agents",
               "predict_split", "suffix")
WINDOW_KEYS = ("seq_len", "stride", "eval_stride", "downsample", "min_agent_steps", "min_agents", "max_agents",
               "max_speed")
RENAMED: dict[str, str] = {
    **{f"data.{k}": f"data.source.{k}" for k in SOURCE_KEYS},
    **{f"data.{k}": f"data.windows.{k}" for k in WINDOW_KEYS},
    **{f"data.{k}": f"protocol.{k}" for k in ("burn_in", "horizons", "burn_in_mode")},
    # the model reads the forecast protocol as one node, ``model.protocol: ${protocol}``
    **{f"model.{k}": f"protocol.{k}" for k in ("burn_in", "horizons", "burn_in_mode", "samples", "miss_threshold")},
}
# Hydra's flags that take a value, and those after which no job runs.
VALUED_FLAGS = {"-cn", "--config-name", "-cp", "--config-path", "-cd", "--config-dir", "-p", "--package",
                "--experimental-rerun"}
NO_RUN_FLAGS = {"-h", "--help", "--hydra-help", "--version", "-sc", "--shell-completion", "-c", "--cfg", "-i",
                "--info", "--resolve"}
CANNOT = re.compile(r"Could not override '([^']+)'")


def nearest_key_message(key: str, value: str, keys: Sequence[str]) -> str:
    """``key=value`` names no key among ``keys`` (the config's, dotted): where 0.2 moved it, else the nearest."""
    if key in RENAMED:
        return f"{key}={value}: no such key; 0.2 moved it to {RENAMED[key]} ({RENAMED[key]}={value})"
    parent = key.rpartition(".")[0]
    siblings = [k for k in keys if k.rpartition(".")[0] == parent]
    near = difflib.get_close_matches(key, keys, n=3, cutoff=0.75) or difflib.get_close_matches(
        key.rpartition(".")[2], [k.rpartition(".")[2] for k in siblings], n=3, cutoff=0.5)
    near = [k if "." in k or not parent else f"{parent}.{k}" for k in near]
    hint = f"did you mean {', '.join(near)}?" if near else (
        f"the keys under {parent}: {', '.join(sorted(k.rpartition('.')[2] for k in siblings)[:12])}" if siblings
        else "")
    return f"{key}={value}: no such key" + (f"; {hint}" if hint else "")


def dotted_keys(node: Any, prefix: str = "") -> list[str]:
    """Every key of a plain config tree, dotted (``model.net.encoder.hidden``)."""
    if not isinstance(node, Mapping):
        return []
    out: list[str] = []
    for k, v in node.items():
        path = f"{prefix}{k}"
        out += [path, *dotted_keys(v, f"{path}.")]
    return out


def job_overrides(argv: Sequence[str]) -> tuple[str, list[str]] | None:
    """(config name, the overrides of one job) of a ``python -m dider.run`` command line; None when it runs no job
    (help, --cfg) or sweeps values (each job is checked by its own preflight)."""
    name, overrides, skip = "config", [], False
    args = list(argv)
    for i, arg in enumerate(args):
        if skip:
            skip = False
            continue
        flag = arg.split("=", 1)[0]
        if flag in NO_RUN_FLAGS:
            return None
        if flag in VALUED_FLAGS:
            if flag in ("-cn", "--config-name"):
                name = arg.split("=", 1)[1] if "=" in arg else args[i + 1] if i + 1 < len(args) else name
            skip = "=" not in arg
            continue
        if arg.startswith("-"):
            continue  # -m / --multirun and other switches
        overrides.append(arg)
    if any("," in o.split("=", 1)[-1] or "(" in o.split("=", 1)[-1] for o in overrides):
        return None
    return name, overrides


def override_problem(argv: Sequence[str]) -> str | None:
    """dider's message for an override of a key the config does not have (with or without a moved key), or None
    (the command line composes, or fails for another reason, which Hydra reports)."""
    job = job_overrides(argv)
    if job is None:
        return None
    name, overrides = job
    try:
        _compose(name, overrides)
        return None
    except ConfigCompositionException as e:
        found = CANNOT.search(str(e))
        if found is None:
            return None
        key = found.group(1)
        given = next((o for o in overrides if o.split("=", 1)[0].lstrip("~") == key), f"{key}=")
        rest = [o for o in overrides if o is not given]
    try:
        keys = dotted_keys(OmegaConf.to_container(_compose(name, rest), resolve=False))
    except ConfigCompositionException:
        keys = []
    return nearest_key_message(key, given.split("=", 1)[1] if "=" in given else "", keys)


def _compose(name: str, overrides: list[str]) -> Any:
    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(version_base="1.3", config_module="dider.conf"):
            return compose(config_name=name, overrides=overrides)
    finally:
        GlobalHydra.instance().clear()
