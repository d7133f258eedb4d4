"""kloppy's tracking data as track rows (``data=soccer``): a provider's files read in metres, each period a scene,
every player (and optionally the ball) an agent of class ``home`` / ``away`` / ``ball``, present where the provider
has a position. kloppy is optional (``pip install 'dider[soccer]'``); errors name ``data.source.provider``,
``data.source.files`` or ``data.source.options``.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

# data.source.provider -> (kloppy module, loader, the loader's file arguments: required, optional).
PROVIDERS: dict[str, tuple[str, str, tuple[str, ...], tuple[str, ...]]] = {
    "hawkeye": ("hawkeye", "load", ("ball_feeds", "player_centroid_feeds"), ("meta_data",)),
    "skillcorner": ("skillcorner", "load", ("meta_data", "raw_data"), ()),
    "metrica_csv": ("metrica", "load_tracking_csv", ("home_data", "away_data"), ()),
    "metrica_epts": ("metrica", "load_tracking_epts", ("meta_data", "raw_data"), ()),
    "tracab": ("tracab", "load", ("meta_data", "raw_data"), ()),
    "sportec": ("sportec", "load_tracking", ("meta_data", "raw_data"), ()),
    "secondspectrum": ("secondspectrum", "load", ("meta_data", "raw_data"), ("additional_meta_data",)),
    "pff": ("pff", "load_tracking", ("meta_data", "roster_meta_data", "raw_data"), ()),
}
CLASSES = ("away", "ball", "home")


def kloppy_sample(name: str) -> str:
    """The path of a sample file that ships inside kloppy's distribution (its test files), e.g.
    ``skillcorner_match_data.json``: the ``${kloppy_sample:NAME}`` config resolver."""
    try:
        kloppy = importlib.import_module("kloppy")
    except ImportError as e:
        raise ImportError(f"kloppy_sample:{name}: kloppy is not installed: pip install 'dider[soccer]' ({e})") from None
    path = Path(kloppy.__file__).parent / "tests" / "files" / name
    if not path.is_file():
        raise FileNotFoundError(f"kloppy_sample:{name}: kloppy {kloppy.__version__} ships no such sample ({path})")
    return str(path)


def kloppy_tracking(provider: str, files: Mapping[str, Any], options: Mapping[str, Any] | None = None) -> Any:
    """The provider's tracking data set, in metres (kloppy's TrackingDataset); errors name the setting."""
    if provider not in PROVIDERS:
        raise ValueError(f"data.source.provider={provider!r}: expected one of {sorted(PROVIDERS)}")
    module, loader, arguments, optional = PROVIDERS[provider]
    if files is not None and not isinstance(files, Mapping):
        raise ValueError(f"data.source.files={files!r}: expected the reader's files by its argument names, e.g. "
                         f"data.source.files={{{arguments[0]}:PATH,{arguments[-1]}:PATH}} for "
                         f"data.source.provider={provider}")
    if options is not None and not isinstance(options, Mapping):
        raise ValueError(f"data.source.options={options!r}: expected keyword arguments of kloppy's loader, e.g. "
                         f"data.source.options={{limit:1000}}")
    given = dict(files or {})
    if unknown := sorted(set(given) - set(arguments) - set(optional)):
        raise ValueError(f"data.source.files: unknown key(s) {unknown} for data.source.provider={provider} (its "
                         f"loader reads {list(arguments)}"
                         + (f", optionally {list(optional)}" if optional else "") + ")")
    if needed := [a for a in arguments if a not in given]:
        raise ValueError(f"data.source.files: data.source.provider={provider} needs {needed} "
                         f"(kloppy.{module}.{loader}'s files)")
    for key, value in given.items():
        for path in value if isinstance(value, (list, tuple)) else [value]:
            where = Path(str(path)).expanduser()
            if not where.exists():
                raise FileNotFoundError(f"data.source.files.{key}={path}: no such file or folder")
            if where.is_file() and where.stat().st_size == 0:
                raise ValueError(f"data.source.files.{key}={path}: the file is empty")
    try:
        kloppy = importlib.import_module(f"kloppy.{module}")
    except ImportError as e:
        raise ImportError(f"data=soccer reads tracking data with kloppy >= 3.19, which is not installed (or too "
                          f"old for data.source.provider={provider}): pip install 'dider[soccer]' ({e})") from None
    read = getattr(kloppy, loader)
    takes = inspect.signature(read).parameters
    if not any(p.kind is p.VAR_KEYWORD for p in takes.values()):
        if unknown := sorted(set(options or {}) - set(takes)):
            raise ValueError(f"data.source.options: kloppy.{module}.{loader} takes no {unknown} (it takes "
                             f"{sorted(k for k in takes if k not in arguments and k not in optional)})")
    paths = {k: [str(Path(str(p)).expanduser()) for p in v] if isinstance(v, (list, tuple))
             else str(Path(str(v)).expanduser()) for k, v in given.items()}
    try:
        return read(**paths, coordinates="secondspectrum", **dict(options or {}))
    except Exception as e:  # kloppy raises many types for a file it cannot parse
        blame = "data.source.options" if options and any(str(k) in str(e) for k in options) else "data.source.files"
        raise ValueError(f"{blame}: kloppy.{module}.{loader} could not read {paths} as data.source.provider={provider} "
                         f"with options {dict(options or {})} ({type(e).__name__}: {e})") from e


def tracking_rows(dataset: Any, ball: bool, source: str) -> tuple[dict[str, Any], float | None]:
    """A kloppy TrackingDataset -> the rows :func:`dider.data.table.table_windows` cuts (scenes = periods,
    agents = players and the ball, classes home / away / ball) and the provider's frame rate (None if unknown)."""
    df = dataset.to_df(engine="pandas")
    grounds = {team.team_id: str(team.ground).lower() for team in dataset.metadata.teams}
    # players of the two teams (a provider may list referees as a team of their own: not agents here)
    team_of = {str(p.player_id): grounds[team.team_id] for team in dataset.metadata.teams for p in team.players
               if grounds[team.team_id] in ("home", "away")}
    players = [c[:-2] for c in df.columns if c.endswith("_x") and c[:-2] in team_of]
    if not players:
        raise ValueError(f"{source}: no player positions in the tracking data ({len(df)} frames)")
    names = players + (["ball"] if ball else [])
    x = df[[f"{p}_x" for p in names]].to_numpy(np.float64)  # [F, A]
    y = df[[f"{p}_y" for p in names]].to_numpy(np.float64)
    frame_i, agent = np.nonzero(np.isfinite(x) & np.isfinite(y))
    periods, scene = np.unique(df["period_id"].to_numpy()[frame_i], return_inverse=True)
    order = np.lexsort((frame_i, agent, scene))
    frame_i, agent, scene = frame_i[order], agent[order], scene[order]
    klass = np.array([CLASSES.index(team_of.get(n, "ball")) for n in names])
    rows = {"scene": scene, "scene_ids": periods.astype(np.int64), "agent": agent.astype(np.int64),
            "frame": df["frame_id"].to_numpy(np.int64)[frame_i], "line": order,
            "xy": np.stack([x[frame_i, agent], y[frame_i, agent]], 1), "vel": None,
            "agent_class": klass[agent], "has_scene": True,
            "names": {"agent": names, "agent_class": list(CLASSES)}}
    rate = dataset.metadata.frame_rate
    return rows, (float(rate) if rate else None)
