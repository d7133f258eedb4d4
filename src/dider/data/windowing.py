"""Cutting a scene's dense grid of steps x agents into windows: what every reader of long tracks shares.

A window of ``seq_len`` steps starts every ``stride`` steps; it keeps the agents present in at least
``min_agent_steps`` of its steps (at most ``max_agents`` of them, those seen longest) and is dropped with fewer
than ``min_agents`` (a relation needs two).
"""

from __future__ import annotations

import numpy as np

# Cap on the dense (steps x agents) grid of one scene: a real inD recording has ~4k steps x ~400 tracks.
MAX_GRID_CELLS = 2**28


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
                 min_agents: int, max_agents: int | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One scene's windows, packed (:func:`cut_windows` decides which).

    grid: [S, K, 4] (x, y, vx, vy; any float dtype), present: [S, K] bool -> states [P, T, 4] float32 (rounded
    once from the grid's values), mask [P, T] bool, counts [W] (agents per window), starts [W] and agent [P]
    int64 (each row's column in the grid), rows by window then agent.
    """
    starts, window, agent = cut_windows(present, seq_len, stride, min_agent_steps, min_agents, max_agents)
    steps = starts[window][:, None] + np.arange(seq_len)[None, :]  # [P, T]
    states = grid[steps, agent[:, None]].astype(np.float32, copy=False)
    return states, present[steps, agent[:, None]], np.bincount(window, minlength=len(starts)), starts, agent
