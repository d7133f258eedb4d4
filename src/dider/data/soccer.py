"""Soccer tracking data through kloppy (``data=soccer``): players, and optionally the ball, as agents in metres.

kloppy (``pip install 'dider[soccer]'``) reads the tracking data of many providers into one model; the
provider's loader is named by ``data.provider`` and its files by ``data.files`` (the loader's own argument
names, e.g. Hawk-Eye's ``ball_feeds`` and ``player_centroid_feeds``). Positions are read in a metric,
pitch-centred coordinate system (kloppy's ``secondspectrum``: metres, x along the pitch), each period is a
scene, every player is an agent (class ``home`` / ``away``, the ball ``ball``), present where the provider
has a position; players come and go (substitutions, a broadcast camera's view) with masks. The frame rate is
the provider's (``data.frame_rate: null``) and travels into the checkpoint, so ``mode=predict`` reads new
matches the same way. The reading is :mod:`dider.data.readers.kloppy`'s; windows, downsampling, the split and the
normalisation are :mod:`dider.data.table`'s.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

from dider.data.readers.kloppy import PROVIDERS, kloppy_tracking, tracking_rows
from dider.data.table import TableDataModule, table_windows
from dider.validation import Rule, check_settings, one_of

log = logging.getLogger(__name__)

# Two recordings whose frame rates differ by less than this share are read as one rate (kloppy infers some
# providers' rates from the timestamps).
RATE_TOLERANCE = 0.02


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
