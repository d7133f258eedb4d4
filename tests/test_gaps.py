"""Agents that leave and come back (tracks with gaps) and agents absent when the forecast starts: a forecast frame is
scored only while the agent has been present since its last observed frame, in the test pass and in prediction
alike, and distances are measured in the data's units at their full precision."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from dider.protocol import scored_targets
from dider.run import predict, train

pytestmark = pytest.mark.usefixtures("one_thread")


def test_scored_targets_by_hand():
    """burn_in 3 over 8 frames. Agent 0 leaves at frame 5 and comes back; agent 1 enters at frame 1; agent 2 misses
    frames 2 and 6."""
    mask = torch.tensor([[1, 1, 1, 1, 1, 0, 1, 1], [0, 1, 1, 1, 1, 1, 1, 1], [1, 1, 0, 1, 1, 1, 0, 1]]).bool()
    mask = mask.T[None]  # [1, T, N]
    # global: observed at frame 2 (the burn-in's last); scored from frame 3 while present since frame 2
    assert scored_targets(mask, 3, "global")[0].T.int().tolist() == [[1, 1, 0, 0, 0], [1, 1, 1, 1, 1],
                                                                     [0, 0, 0, 0, 0]]
    # per agent: each after its own 3rd present frame, while present since then
    assert scored_targets(mask, 3, "per_agent")[0].T.int().tolist() == [[1, 1, 0, 0, 0], [0, 1, 1, 1, 1],
                                                                        [0, 1, 1, 0, 0]]


def straight_tracks_with_gaps(path: Path, scenes: int = 40, frames: int = 16) -> Path:
    """Vessels on straight lines at constant speed over a few kilometres (metres): in each scene agent 1 is missing
    for frames 8-9 and agent 2 for frames 4-5 (around the burn-in's end), agent 0 is tracked throughout."""
    rng = np.random.default_rng(2)
    rows = []
    for scene in range(scenes):
        for agent in range(3):
            start = np.array([2000.0, 3000.0]) + rng.uniform(0, 5000, 2)
            velocity = rng.uniform(-8, 8, 2)
            missing = {1: (8, 9), 2: (4, 5)}.get(agent, ())
            rows += [(scene, agent, f, *(start + velocity * f)) for f in range(frames) if f not in missing]
    pd.DataFrame(rows, columns=["scene", "agent", "frame", "x", "y"]).to_csv(path, index=False)
    return path


@pytest.mark.parametrize("mode", ["per_agent", "global"])
def test_constant_velocity_scores_zero_on_straight_tracks_with_gaps(make_cfg, tmp_path, mode):
    path = straight_tracks_with_gaps(tmp_path / "vessels.csv")
    data = ["data=table", f"data.source.path={path}", "data.source.frame_rate=1", "data.windows.seq_len=15",
            "protocol.burn_in=5",
            "protocol.horizons=[1,5,8]", f"protocol.burn_in_mode={mode}"]
    run = tmp_path / "run"
    metrics = train(make_cfg(["experiment=smoke", *data, "logger=none", "callbacks.timelines.num_clips=0"],
                             tiny=False, out=run))
    for h in (1, 5, 8):
        assert metrics[f"test/cv/ade/h{h:02d}"] < 0.01, metrics  # metres, on tracks 1-8 m a step
        assert metrics[f"test/ade/h{h:02d}"] > 0.01  # the one-epoch model does not
    predict(make_cfg(["mode=predict", f"ckpt_path={run}", *data[:5], "predict.forecast_steps=8"], tiny=False,
                     out=tmp_path / "predicted"))
    scores = json.loads((tmp_path / "predicted" / "predictions" / "forecast_scores.json").read_text())
    scores = scores.get("scores", scores)
    assert scores["predict/cv/ade/h08"] < 0.01 and scores["predict/ade/h08"] > 0.01


def test_distances_in_data_units_keep_the_last_digits():
    """Positions near 5e6 m (UTM northings) 0.3 m apart: in float32 a step there is 0.5 m, so the distance would read
    0 or 0.5; the data units are float64."""
    from dider.data.batch import Normalizer
    from dider.evaluation.scoring import data_units

    units = data_units(Normalizer((5.0e6, 5.0e6 + 100.0), (-1.0, 1.0)))
    a = torch.tensor([[0.5, 0.5, 0.0, 0.0]])
    b = a + torch.tensor([[0.006, 0.0, 0.0, 0.0]])  # 0.006 normalised units = 0.3 m
    assert abs(float((units(b) - units(a))[0, 0]) - 0.3) < 1e-3
