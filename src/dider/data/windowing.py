"""Cutting a scene's dense grid of steps x agents into windows: what every reader of long tracks shares.

A window of ``seq_len`` steps starts every ``stride`` steps; it keeps the agents present in at least
``min_agent_steps`` of its steps (at most ``max_agents`` of them, those seen longest) and is dropped with fewer
than ``min_agents`` (a relation needs two).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields, replace
from typing import Any, ClassVar

import numpy as np

from dider.validation import ConfigError, Rule, above, check_settings, integer, optional

# Cap on the dense (steps x agents) grid of one scene: a real inD recording has ~4k steps x ~400 tracks.
MAX_GRID_CELLS = 2**28


@dataclass(frozen=True)
class Windows:
    """How a data set of long tracks is cut into clips: the data config's ``windows`` node. A data module's class
    holds its data set's defaults (``WINDOWS``); the node overrides them key by key."""

    seq_len: int = 20  # steps per window
    stride: int | None = None  # a (training) window starts every ``stride`` steps; null: seq_len (no overlap)
    eval_stride: int | None = None  # the same for val / test where recordings are split before the cut (levelX)
    downsample: int = 1  # keep every k-th frame: a step is ``downsample`` frames
    min_agent_steps: int = 1  # a window keeps the agents present in at least this many of its steps
    min_agents: int = 2  # a window with fewer agents kept is dropped (a relation needs two)
    max_agents: int | None = None  # at most this many agents per window, those present longest (levelX)
    max_speed: float | None = None  # a faster step (data units per second) is a tracking jump: absent (tables)

    MIN_SEQ_LEN: ClassVar[int] = 2  # a window needs one transition
    SETTINGS: ClassVar[dict[str, Rule]] = {
        "seq_len": integer(MIN_SEQ_LEN), "stride": optional(integer(1)), "eval_stride": optional(integer(1)),
        "downsample": integer(1), "min_agent_steps": integer(1), "min_agents": integer(1),
        "max_agents": optional(integer(1)), "max_speed": optional(above(0)),
    }

    def __post_init__(self) -> None:
        check_settings(self, asdict(self), key="data.windows")
        if self.min_agent_steps > self.seq_len:
            raise ConfigError(f"data.windows.min_agent_steps={self.min_agent_steps}: must be <= "
                              f"data.windows.seq_len={self.seq_len}")
        if self.max_agents is not None and self.max_agents < self.min_agents:
            raise ConfigError(f"data.windows.max_agents={self.max_agents}: must be >= "
                              f"data.windows.min_agents={self.min_agents}")

    @classmethod
    def of(cls, defaults: Windows, given: Mapping[str, Any] | None, unused: Mapping[str, str]) -> Windows:
        """``defaults`` overridden by the config's node key by key; a key of ``unused`` (name -> why this data set
        does not read it) may not be set."""
        given = dict(given or {})
        names = [f.name for f in fields(cls)]
        if unknown := sorted(set(given) - set(names)):
            raise ConfigError(f"data.windows: no such setting(s) {unknown} (expected some of {names})")
        if wrong := [f"data.windows.{k}={given[k]!r}: {why}" for k, why in unused.items() if given.get(k) is not None]:
            raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(wrong))
        return replace(defaults, **given)


def cut_windows(present: np.ndarray, seq_len: int, stride: int, min_agent_steps: int, min_agents: int,
                max_agents: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The windows of one scene and the agents each keeps.

    present: [S, K] bool (steps x agents, agents in the order the windows keep them) -> starts [W] int64 (first
    step of each kept window), window [P] and agent [P] int64: the kept (window, agent) pairs, by window then
    agent.
    """
    num_steps, k = present.shape
    starts = np.arange(0, num_steps - seq_len + 1, stride)
    # Steps each agent is present in each window, from a cumulative sum over time: [W, K].
    csum = np.zeros((num_steps + 1, k), np.int32)  # counts <= num_steps (< 2**28): int32 halves the memory
    np.cumsum(present, axis=0, out=csum[1:])
    steps_in = csum[starts + seq_len] - csum[starts]
    kept = steps_in >= min_agent_steps
    if max_agents is not None:
        # Keep the agents seen longest in the window (ties: the earlier agent): rank them per window.
        score = np.where(kept, steps_in.astype(np.int64) * (k + 1) + (k - np.arange(k)), -1)
        order = np.argsort(-score, axis=1, kind="stable")
        rank = np.empty_like(order)
        np.put_along_axis(rank, order, np.arange(k)[None, :].repeat(len(starts), 0), axis=1)
        kept &= rank < max_agents
    good = kept.sum(1) >= min_agents
    window, agent = np.nonzero(kept[good])
    return starts[good], window, agent


def grid_windows(grid: np.ndarray, present: np.ndarray, seq_len: int, stride: int, min_agent_steps: int,
                 min_agents: int, max_agents: int | None = None, origin: tuple[float, float] = (0.0, 0.0)
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One scene's windows, packed (:func:`cut_windows` decides which).

    grid: [S, K, 4] (x, y, vx, vy; any float dtype), present: [S, K] bool -> states [P, T, 4] float32 (positions
    less ``origin``, taken in the grid's dtype before the one rounding to float32, so that large coordinates keep
    their precision; zeros where absent), mask [P, T] bool, counts [W] (agents per window), starts [W] and agent
    [P] int64 (each row's column in the grid), rows by window then agent.
    """
    starts, window, agent = cut_windows(present, seq_len, stride, min_agent_steps, min_agents, max_agents)
    steps = starts[window][:, None] + np.arange(seq_len)[None, :]  # [P, T]
    states, mask = grid[steps, agent[:, None]], present[steps, agent[:, None]]
    if origin != (0.0, 0.0):
        states = states - np.array([origin[0], origin[1], 0.0, 0.0]) * mask[..., None]
    return (states.astype(np.float32, copy=False), mask, np.bincount(window, minlength=len(starts)), starts,
            agent)


def midpoint(xy: np.ndarray) -> tuple[float, float]:
    """The centre of the bounding box of positions xy [R, 2] (float64): the origin a source's windows are
    relative to (:class:`~dider.data.batch.Normalizer`)."""
    if not len(xy):
        return (0.0, 0.0)
    lo, hi = xy.min(0).astype(np.float64), xy.max(0).astype(np.float64)
    mid = lo / 2 + hi / 2  # halves first: no overflow near float64's range
    return (float(mid[0]), float(mid[1]))
