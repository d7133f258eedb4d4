"""Cutting a scene's grid of steps x agents into windows (shared by the table and levelX readers), by hand."""

from __future__ import annotations

import numpy as np

from dider.data.windowing import cut_windows


def grid() -> np.ndarray:
    """6 steps x 3 agents: agent 0 always there, agent 1 at steps 0-2, agent 2 at steps 2-5."""
    present = np.zeros((6, 3), bool)
    present[:, 0] = True
    present[0:3, 1] = True
    present[2:6, 2] = True
    return present


def test_windows_keep_agents_present_long_enough() -> None:
    """Windows of 3 steps every 3: [0, 3) has agents 0 (3 steps), 1 (3), 2 (1); [3, 6) has 0 (3), 2 (3).
    At least 2 steps: window 0 keeps agents 0 and 1, window 1 agents 0 and 2."""
    starts, window, agent = cut_windows(grid(), seq_len=3, stride=3, min_agent_steps=2, min_agents=2)
    assert starts.tolist() == [0, 3] and window.tolist() == [0, 0, 1, 1] and agent.tolist() == [0, 1, 0, 2]


def test_windows_with_too_few_agents_are_dropped_and_the_rest_renumbered() -> None:
    """Windows of 2 every 2 with 2 steps needed: [0, 2) keeps agents 0, 1; [2, 4) agents 0, 2 (agent 1 is there
    one step); [4, 6) agents 0, 2. With one step enough and 3 agents needed only [2, 4) is left, renumbered 0;
    with 2 steps and 3 agents none."""
    starts, window, agent = cut_windows(grid(), seq_len=2, stride=2, min_agent_steps=2, min_agents=2)
    assert starts.tolist() == [0, 2, 4] and agent.tolist() == [0, 1, 0, 2, 0, 2]
    starts, window, agent = cut_windows(grid(), seq_len=2, stride=2, min_agent_steps=1, min_agents=3)
    assert starts.tolist() == [2] and window.tolist() == [0, 0, 0] and agent.tolist() == [0, 1, 2]
    assert cut_windows(grid(), 2, 2, 2, 3)[0].size == 0


def test_max_agents_keeps_those_seen_longest_ties_to_the_earlier() -> None:
    """One window of all 6 steps: agent 0 6 steps, 2 four, 1 three. Two at most: 0 and 2; then with agent 1
    present as long as agent 2 (ties), the earlier agent, 1, wins."""
    _, _, agent = cut_windows(grid(), seq_len=6, stride=6, min_agent_steps=1, min_agents=2, max_agents=2)
    assert agent.tolist() == [0, 2]
    tie = grid()
    tie[3, 1] = True  # agent 1: 4 steps, as many as agent 2
    _, _, agent = cut_windows(tie, seq_len=6, stride=6, min_agent_steps=1, min_agents=2, max_agents=2)
    assert agent.tolist() == [0, 1]
