"""Soccer tracking data through kloppy (``data=soccer``): players, and optionally the ball, as agents in metres.

kloppy (``pip install 'dider[soccer]'``) reads the tracking data of many providers into one model; the
provider's loader is named by ``data.provider`` and its files by ``data.files`` (the loader's own argument
names, e.g. Hawk-Eye's ``ball_feeds`` and ``player_centroid_feeds``). Positions are read in a metric,
pitch-centred coordinate system (kloppy's ``secondspectrum``: metres, x along the pitch), each period is a
scene, every player is an agent (class ``home`` / ``away``, the ball ``ball``), present where the provider
has a position; players come and go (substitutions, a broadcast camera's view) with masks. The frame rate is
the provider's (``data.frame_rate: null``) and travels into the checkpoint, so ``mode=predict`` reads new
matches the same way. Windows, downsampling, the split and the normalisation are :mod:`dider.data.table`'s.
"""

from __future__ import annotations

import importlib
import inspect
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from dider.data.table import TableDataModule, table_windows
from dider.validation import Rule, check_settings, one_of

log = logging.getLogger(__name__)

# data.provider -> (kloppy module, loader, the loader's file arguments: required, optional).
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
# Two recordings whose frame rates differ by less than this share are read as one rate (kloppy infers some
# providers' rates from the timestamps).
RATE_TOLERANCE = 0.02
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
        raise ValueError(f"data.provider={provider!r}: expected one of {sorted(PROVIDERS)}")
    module, loader, arguments, optional = PROVIDERS[provider]
    if files is not None and not isinstance(files, Mapping):
        raise ValueError(f"data.files={files!r}: expected the reader's files by its argument names, e.g. "
                         f"data.files={{{arguments[0]}:PATH,{arguments[-1]}:PATH}} for data.provider={provider}")
    if options is not None and not isinstance(options, Mapping):
        raise ValueError(f"data.options={options!r}: expected keyword arguments of kloppy's loader, e.g. "
                         f"data.options={{limit:1000}}")
    given = dict(files or {})
    if unknown := sorted(set(given) - set(arguments) - set(optional)):
        raise ValueError(f"data.files: unknown key(s) {unknown} for data.provider={provider} (its loader reads "
                         f"{list(arguments)}" + (f", optionally {list(optional)}" if optional else "") + ")")
    if needed := [a for a in arguments if a not in given]:
        raise ValueError(f"data.files: data.provider={provider} needs {needed} (kloppy.{module}.{loader}'s files)")
    for key, value in given.items():
        for path in value if isinstance(value, (list, tuple)) else [value]:
            where = Path(str(path)).expanduser()
            if not where.exists():
                raise FileNotFoundError(f"data.files.{key}={path}: no such file or folder")
            if where.is_file() and where.stat().st_size == 0:
                raise ValueError(f"data.files.{key}={path}: the file is empty")
    try:
        kloppy = importlib.import_module(f"kloppy.{module}")
    except ImportError as e:
        raise ImportError(f"data=soccer reads tracking data with kloppy >= 3.19, which is not installed (or too "
                          f"old for data.provider={provider}): pip install 'dider[soccer]' ({e})") from None
    read = getattr(kloppy, loader)
    takes = inspect.signature(read).parameters
    if not any(p.kind is p.VAR_KEYWORD for p in takes.values()):
        if unknown := sorted(set(options or {}) - set(takes)):
            raise ValueError(f"data.options: kloppy.{module}.{loader} takes no {unknown} (it takes "
                             f"{sorted(k for k in takes if k not in arguments and k not in optional)})")
    paths = {k: [str(Path(str(p)).expanduser()) for p in v] if isinstance(v, (list, tuple))
             else str(Path(str(v)).expanduser()) for k, v in given.items()}
    try:
        return read(**paths, coordinates="secondspectrum", **dict(options or {}))
    except Exception as e:  # kloppy raises many types for a file it cannot parse
        blame = "data.options" if options and any(str(k) in str(e) for k in options) else "data.files"
        raise ValueError(f"{blame}: kloppy.{module}.{loader} could not read {paths} as data.provider={provider} "
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


class SoccerDataModule(TableDataModule):
    """Windows of a match's tracking data read through kloppy (see the module docstring). Batches and
    attributes as :class:`~dider.data.table.TableDataModule`'s; ``agent_class`` is each agent's team (or the
    ball); after reading, ``hparams.frame_rate`` is the provider's rate, which the features were computed at."""

    # the table's settings but its reader (kloppy reads the provider's files)
    SETTINGS: ClassVar[dict[str, Rule | type]] = {k: v for k, v in TableDataModule.SETTINGS.items()
                                                   if k != "reader"} | {
        "provider": one_of(*sorted(PROVIDERS)),
        "frame_rate": lambda value: None if value is None or TableDataModule.SETTINGS["frame_rate"](value) is None
        else "must be null (the provider's) or a number > 0",
    }
    units = "m"  # kloppy's metric pitch coordinates

    def __init__(
        self,
        provider: str = "hawkeye",
        files: Mapping[str, Any] | None = None,
        options: Mapping[str, Any] | None = None,
        ball: bool = False,
        frame_rate: float | None = None,
        downsample: int = 1,
        seq_len: int = 20,
        stride: int | None = None,
        min_agent_steps: int = 1,
        min_agents: int = 2,
        split: Sequence[float] = (0.8, 0.1, 0.1),
        seed: int = 1,
        num_train: int | None = None,
        num_val: int | None = None,
        num_test: int | None = None,
        loader: Mapping[str, Any] | None = None,
        cache_dir: str | None = None,
        max_speed: float | None = 12.0,
    ) -> None:
        """provider: kloppy's reader: hawkeye, skillcorner, metrica_csv, metrica_epts, tracab, sportec,
        secondspectrum or pff.
        files: the reader's files by its argument names (required), e.g. Hawk-Eye's {ball_feeds: F,
        player_centroid_feeds: G}: a file, a list of files, or a folder where the reader takes one.
        options: further keyword arguments of the kloppy loader (e.g. ``sample_rate``, ``limit``, ``only_alive``).
        ball: the ball as one more agent (class ``ball``).
        frame_rate: null takes the provider's (a value given must match it).
        downsample: keep every k-th frame, e.g. 8 turns 50 Hz into 6.25 Hz steps.
        max_speed: m/s: a faster step is a tracking jump (players sprint at <= 11 m/s), the player absent there;
        with ``ball: true``, >= 40.
        cache_dir: unused (kloppy reads the files each run).
        The other settings as :class:`~dider.data.table.TableDataModule`'s."""
        check_settings(self, locals(), key="data")
        super().__init__(None, None, frame_rate or 1.0, downsample, seq_len, stride, min_agent_steps, min_agents,
                         split, seed, num_train, num_val, num_test, loader, cache_dir, max_speed)
        self._rows: dict[str, Any] | None = None

    def _source(self) -> str:
        return f"data.provider={self.hparams.provider} data.files={dict(self.hparams.files or {})}"

    def _read(self) -> dict[str, Any]:
        if self._rows is None:
            h = self.hparams
            dataset = kloppy_tracking(h.provider, h.files, h.options)
            self._rows, rate = tracking_rows(dataset, h.ball, self._source())
            if rate is None and h.frame_rate is None:
                raise ValueError(f"{self._source()}: the tracking data give no frame rate; set data.frame_rate")
            if rate is not None and h.frame_rate is not None and abs(rate - h.frame_rate) > RATE_TOLERANCE * rate:
                raise ValueError(f"data.frame_rate={h.frame_rate} (given, or a checkpoint's in prediction): the "
                                 f"tracking data run at {rate} frames per second; leave it null to use theirs (in "
                                 f"prediction, set data.frame_rate and data.downsample to the same step rate as "
                                 f"the checkpoint's, with predict.force=true)")
            if h.frame_rate is None:  # recorded, so that the checkpoint (and prediction) carries the rate
                h.frame_rate = rate
                self.dt = h.downsample / rate
            log.info("%s: %d players%s over %d period(s) at %s Hz", self._source(),
                     len(self._rows["names"]["agent"]) - int(h.ball), " and the ball" if h.ball else "",
                     len(self._rows["scene_ids"]), h.frame_rate)
        return self._rows

    def _windows(self) -> dict[str, Any]:
        rows = self._read()  # first: it fixes data.frame_rate, which the windows' velocities use
        h = self.hparams
        data = table_windows(rows, self._source(), h.frame_rate, h.downsample, h.seq_len, h.stride or h.seq_len,
                             h.min_agent_steps, h.min_agents, h.max_speed)
        self.source_names = {"agent": rows["names"]["agent"]}
        return data
