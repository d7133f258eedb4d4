"""Older data configs read as today's: a run folder's saved config (``.hydra/config.yaml``) or a checkpoint's data
arguments written by an earlier version, for the tools that rebuild its data module (``dider.analysis.diagnose``),
and a checkpoint's data settings as one flat view (:func:`flat_view`) whatever its version."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields
from typing import Any

from dider.data.loader import Loader
from dider.data.windowing import Windows

# The forecast protocol's keys, which data configs once carried beside the model (today the model's alone).
PROTOCOL_KEYS = ("burn_in", "horizons", "burn_in_mode")
TABLE = "dider.data.table.TableDataModule"
LEVELX = "dider.data.ind.InDDataModule"
TRACKS = "dider.data.tracks.TracksDataModule"
CLIPS_DM = "dider.data.clips.ClipsDataModule"
NRI = "dider.data.nri.NRIDataModule"
# The data modules of older versions, by their target: (today's target, the source's keys that were flat (old name ->
# today's path under ``source``), the reader of the source where the config names none).
FLAT: dict[str, tuple[str, dict[str, str], str | None]] = {
    "dider.data.synth.SynthDataModule": (
        CLIPS_DM, {k: k for k in ("num_steps", "push_factor", "push", "seed")}, "push"),
    "dider.data.trajectories.TrajectoryDataModule": (CLIPS_DM, {k: k for k in ("path", "frame_rate")}, "trajectories"),
    "dider.data.basketball.BasketballDataModule": (
        CLIPS_DM, {k: k for k in ("root", "format", "agents", "frame_rate")}, "basketball"),
    "dider.data.dnri_files.DNRIFilesDataModule": (CLIPS_DM, {k: k for k in ("root", "predict_split")}, "dnri_files"),
    NRI: (CLIPS_DM, {"root": "root", "suffix": "suffix"}, "particles"),
    TABLE: (TRACKS, {k: k for k in ("reader", "path", "columns", "frame_rate")}, None),
    "dider.data.soccer.SoccerDataModule": (
        TRACKS, {k: k for k in ("provider", "files", "options", "ball", "frame_rate")}, "kloppy"),
    LEVELX: (TRACKS, {
        **{k: k for k in ("root", "name", "recordings", "classes", "background_scale")},
        **{f"{k}_pattern": f"files.{k}" for k in ("tracks", "tracks_meta", "recording_meta", "background")},
        "track_id_column": "columns.track_id", "frame_column": "columns.frame", "class_column": "columns.agent_class",
        "frame_rate_column": "columns.frame_rate", "features": "columns.features"}, "levelx"),
}
# What the levelX module read from its class where its config said nothing: the loader's batches and the consistency
# check (``pairs: null`` was its default rules; today it is no check).
LEVELX_DEFAULTS = {"loader": {"batch_size": 8, "eval_batch_size": 8}, "pairs": {}}
WINDOW_KEYS = tuple(f.name for f in fields(Windows))


def nest_args(target: str, args: Mapping[str, Any]) -> tuple[str, dict[str, Any]]:
    """A data module's arguments in an older version's layout as today's target and nested arguments: the source's
    keys under ``source`` (NRI's ``simulate`` node: the simulation's) with the reader they were read with, the cut's
    under ``windows``; arguments already nested are kept."""
    new_target, source_keys, reader = FLAT[target]
    if target == LEVELX:  # key by key under what the config gives
        args = {**args, "loader": {**LEVELX_DEFAULTS["loader"], **dict(args.get("loader") or {})},
                "pairs": dict(LEVELX_DEFAULTS["pairs"]) if args.get("pairs") is None else args["pairs"]}
    if target == NRI and args.get("simulate") is not None:
        args = {k: v for k, v in args.items() if k not in ("simulate", "root", "suffix")} | {
            "source": {"reader": "particles", **dict(args["simulate"]), **dict(args.get("source") or {})}}
    elif target == NRI:
        # ``simulate: null`` (or NRI's file settings) read the files; no simulate at all: the default simulation
        reader = "nri_files" if "simulate" in args or args.get("root") is not None or "suffix" in args else reader
        args = {k: v for k, v in args.items() if k != "simulate"}
    out: dict[str, Any] = {}
    source: dict[str, Any] = {}
    windows: dict[str, Any] = {}
    for key, value in args.items():
        if key in source_keys:
            *parents, leaf = source_keys[key].split(".")
            node = source
            for parent in parents:
                node = node.setdefault(parent, {})
            node[leaf] = value
        elif key in WINDOW_KEYS:
            windows[key] = value
        else:
            out[key] = value
    if source or reader:  # the reader they were read with (a node already nested names its own)
        out["source"] = {**({"reader": reader} if reader else {}), **source, **dict(out.get("source") or {})}
    if windows:
        out["windows"] = {**windows, **dict(out.get("windows") or {})}
    return new_target, out


def upgrade_data_node(data: Mapping[str, Any]) -> dict[str, Any]:
    """A data config (plain) in today's layout: the loader's settings in its ``loader`` node where an older config
    has them at the top (``batch_size``, ``eval_batch_size``, ``num_workers``, ``pin_memory``), without the
    forecast protocol's keys (``burn_in``, ``horizons``, ``burn_in_mode``: the model's), and the flat settings of
    a data set nested (:func:`nest_args`)."""
    names = [f.name for f in fields(Loader)]
    node = {k: v for k, v in data.items() if k not in names and k not in PROTOCOL_KEYS}
    if older := {k: data[k] for k in names if k in data}:
        node["loader"] = {**older, **dict(data.get("loader") or {})}
    if (target := node.get("_target_")) in FLAT:
        node["_target_"], nested = nest_args(target, {k: v for k, v in node.items() if k != "_target_"})
        node = {"_target_": node["_target_"], **nested}
    return node


def flat_view(args: Mapping[str, Any]) -> dict[str, Any]:
    """A data module's arguments as one flat mapping (the layout of older checkpoints): the settings of its
    ``source`` and ``windows`` nodes at the top, beside its own."""
    flat = {k: v for k, v in args.items() if k not in ("source", "windows")}
    flat |= {k: v for k, v in dict(args.get("windows") or {}).items() if k not in flat}
    # the source's own over the module's: a simulator's ``seed`` is the data seed, as older checkpoints record it
    return flat | dict(args.get("source") or {})
