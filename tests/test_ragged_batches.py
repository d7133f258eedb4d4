"""Windows padded per batch, so that evaluation batches differ in their largest agent count (tables, inD, soccer): the
test pass and a prediction write every clip's results, padded to one agent count."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from dider.run import predict, train

pytestmark = pytest.mark.usefixtures("one_thread")


def scenes_of_three_and_four(path: Path, scenes: int = 80, frames: int = 13) -> Path:
    """``scenes`` scenes of ``frames`` frames: even scenes hold 3 agents, odd ones 4, each on a straight line."""
    rng = np.random.default_rng(1)
    rows = []
    for scene in range(scenes):
        for agent in range(3 + scene % 2):
            start, velocity = rng.uniform(-5, 5, 2), rng.normal(0, 0.3, 2)
            rows += [(scene, agent, f, *(start + velocity * f)) for f in range(frames)]
    pd.DataFrame(rows, columns=["scene", "agent", "frame", "x", "y"]).to_csv(path, index=False)
    return path


def test_batches_of_different_agent_counts_are_tested_and_predicted(make_cfg, tmp_path):
    path = scenes_of_three_and_four(tmp_path / "tracks.csv")
    table = ["experiment=smoke", "data=table", f"data.source.path={path}", "data.windows.seq_len=12",
             "protocol.horizons=[1,5]",
             "data.loader.eval_batch_size=2", "logger=none", "callbacks.timelines.num_clips=0"]
    run = tmp_path / "run"
    train(make_cfg(table, tiny=False, out=run))
    clips = json.loads((run / "segments.json").read_text())["clips"]
    with np.load(run / "clips.npz") as arrays:
        agents = arrays["mask"].any(1).sum(-1)  # [S] agents present in each written clip
        assert arrays["positions"].shape[2] == 4 and {3, 4} <= set(agents.tolist())
    test = len(clips)
    assert test > 2 and "test/ade/h05" in json.loads((run / "metrics.json").read_text())["metrics"]

    out = tmp_path / "predicted"
    written = predict(make_cfg(["mode=predict", f"ckpt_path={run}", "data=table", f"data.source.path={path}",
                                "data.windows.seq_len=12", "data.loader.eval_batch_size=2", "predict.forecast_steps=5"],
                               tiny=False, out=out))
    assert {p.name for p in written} >= {"clips.npz", "forecast.csv", "segments.csv"}
    with np.load(out / "predictions" / "clips.npz") as arrays:
        assert arrays["positions"].shape[0] == 80 and arrays["positions"].shape[2] == 4  # one window a scene
        assert sorted(set(arrays["mask"].any(1).sum(-1).tolist())) == [3, 4]
    forecast = pd.read_csv(out / "predictions" / "forecast.csv")
    assert forecast.groupby("clip").agent.nunique().value_counts().to_dict() == {3: 40, 4: 40}
