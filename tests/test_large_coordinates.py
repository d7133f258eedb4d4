"""Coordinates of any size: tracks in UTM-sized coordinates (5e6 m, 1e7 m) train, score and predict as the same
tracks near 0 do, and what leaves dider is in the user's coordinates."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from dider.data.batch import Normalizer
from dider.data.readers.trajectories import trajectory_states
from dider.data.table import table_windows
from dider.data.table_reading import read_table
from dider.data.windowing import Windows, midpoint
from dider.run import predict, train

pytestmark = pytest.mark.usefixtures("one_thread")

COLUMNS = {"agent": "agent", "frame": "frame", "x": "x", "y": "y", "scene": "scene"}


def turning_vessels(path: Path, offset: float, scenes: int = 12, frames: int = 24, scale: float = 1.0) -> Path:
    """Three agents a scene on circles of 15-40 m radius at 3-6 m/s, 1 frame a second (constant velocity misses
    the turn by ~1 m a step: errors of centimetres matter), every position times ``scale`` plus ``offset`` in x
    and y."""
    rng = np.random.default_rng(5)
    rows = []
    for scene in range(scenes):
        for agent in range(3):
            centre, radius = rng.uniform(0, 300, 2), rng.uniform(15, 40)
            rate, phase = rng.uniform(3, 6) / radius * rng.choice([-1, 1]), rng.uniform(0, 2 * np.pi)
            angle = phase + rate * np.arange(frames)
            x, y = centre[0] + radius * np.cos(angle), centre[1] + radius * np.sin(angle)
            rows += [(scene, agent, f, x[f] * scale + offset, y[f] * scale + offset) for f in range(frames)]
    pd.DataFrame(rows, columns=["scene", "agent", "frame", "x", "y"]).to_csv(
        path, index=False, float_format="%.6f" if scale == 1 else "%.17g")
    return path


@pytest.mark.parametrize("offset", [5e6, 1e7])
def test_windows_are_the_same_relative_to_the_tables_centre(tmp_path, offset):
    """The cut of a table offset by 5e6 / 1e7 equals the cut of the table itself to micrometres: the origin is
    subtracted in float64, before the float32 rounding (which is 0.5 m at 5e6, 1 m at 1e7)."""
    w = Windows(seq_len=12, stride=12)
    cuts = []
    for shift in (0.0, offset):
        table = read_table(turning_vessels(tmp_path / f"t{shift:g}.csv", shift), COLUMNS)
        origin = midpoint(table["xy"])
        cuts.append(table_windows(table, "t.csv", 1.0, w, range(12), 12, origin).states.double().numpy())
    np.testing.assert_allclose(cuts[1], cuts[0], atol=2e-5)
    assert np.abs(cuts[0][..., :2]).max() < 400  # relative: the table's extent, not its offset


def test_normalizer_round_trips_the_users_coordinates():
    norm = Normalizer((-100.0, 100.0), (-5.0, 5.0), origin=(5.0e6 + 0.25, 1.0e7 - 0.125))
    user = torch.tensor([[5.0e6 + 12.345678, 1.0e7 - 3.210987, 1.5, -2.0]], dtype=torch.float64)
    arrays = {"positions": user[None, None, :, :2].expand(1, 1, 2, 2).numpy(),  # two agents, as the API takes them
              "velocities": user[None, None, :, 2:].expand(1, 1, 2, 2).numpy()}
    raw = trajectory_states(arrays, "clip", 1.0, norm.origin)["states"][0, 0, :1]  # the API's door in
    back = norm.to_user(norm.denormalize(norm.normalize(raw)))
    np.testing.assert_allclose(back.numpy(), user.numpy(), rtol=0, atol=2e-5)
    assert Normalizer(**norm.state_dict()).origin == norm.origin  # travels in checkpoints


def _run(make_cfg, tmp_path: Path, offset: float, scale: float = 1.0) -> tuple[dict, Path, Path]:
    path = turning_vessels(tmp_path / f"vessels_{offset:g}_{scale:g}.csv", offset, scale=scale)
    data = ["data=table", f"data.source.path={path}", "data.source.frame_rate=1", "data.windows.seq_len=12",
            "data.windows.stride=4", "protocol.burn_in=4", "protocol.horizons=[1,4,8]"]
    run = tmp_path / f"run_{offset:g}_{scale:g}"
    metrics = train(make_cfg(["experiment=smoke", *data, "logger=none", "callbacks.timelines.num_clips=0"],
                             tiny=False, out=run))
    return metrics, run, path


def test_a_table_offset_by_5e6_scores_and_predicts_as_the_original(make_cfg, tmp_path):
    original, _, _ = _run(make_cfg, tmp_path, 0.0)
    offset, run, path = _run(make_cfg, tmp_path, 5e6)
    cv = [k for k in original if "/cv/" in k]
    assert len(cv) >= 6
    for key in cv:  # constant velocity: the same arithmetic on the same relative positions
        assert offset[key] == pytest.approx(original[key], rel=1e-4), key
    for key in (k for k in original if k.startswith("test/") and ("/ade/" in k or "/fde/" in k or "/mse/" in k)):
        assert offset[key] == pytest.approx(original[key], rel=0.05, abs=1e-3), key  # the model: within noise

    out = tmp_path / "predicted"
    predict(make_cfg(["mode=predict", f"ckpt_path={run}", "data=table", f"data.source.path={path}",
                      "data.source.frame_rate=1", "data.windows.seq_len=12", "data.windows.stride=4",
                      "predict.forecast_steps=4"], tiny=False, out=out))
    clips = np.load(out / "predictions" / "clips.npz")
    table = pd.read_csv(path)
    first = table[(table.scene == 0) & (table.agent == 0)].sort_values("frame")
    # clip 0 of the table: scene 0's first window, its step 0 the table's frame 1 (frame 0 went to velocities)
    np.testing.assert_allclose(clips["positions"][0, :, 0], first[["x", "y"]].to_numpy()[1:13], rtol=0, atol=1e-3)
    forecast = pd.read_csv(out / "predictions" / "forecast.csv")
    assert forecast["x"].between(5e6 - 100, 5e6 + 500).all() and forecast["y"].between(5e6 - 100, 5e6 + 500).all()
    scores = json.loads((out / "predictions" / "forecast_scores.json").read_text())
    scores = scores.get("scores", scores)
    assert 0.05 < scores["predict/cv/ade/h04"] < 20  # metres: a turn's miss, not a rounding to 0.5 m steps

    # Coordinates of 1e28: the normalised clips are the same, so every data-unit metric is the original's times
    # the scale (squares: its square, beyond float32's 3.4e38): nothing overflows.
    huge, _, _ = _run(make_cfg, tmp_path, 0.0, scale=1e27)
    for key in ("test/cv/ade/h04", "test/ade/h04", "test/fde/h08", "test/mse_raw/h04"):
        power = 2 if "mse_raw" in key else 1
        assert huge[key] == pytest.approx(original[key] * 1e27**power, rel=1e-3), key


def test_an_npz_of_utm_sized_positions_trains_and_predicts_as_the_original(make_cfg, tmp_path):
    """data=trajectories: the file's clips relative to its centre (float64 before the cast): the same metrics as
    the file near 0 (constant velocity's to 1e-4), and predictions in the file's coordinates."""
    from helpers.fixtures import write_trajectories

    near = write_trajectories(tmp_path / "near.npz", num=48, steps=16, agents=3)
    far = {k: v + 5e6 if k == "positions" else v for k, v in near.items()}
    np.savez(tmp_path / "far.npz", **far)
    runs = {}
    for name in ("near", "far"):
        data = ["data=trajectories", f"data.source.path={tmp_path / f'{name}.npz'}", "protocol.burn_in=4",
                "protocol.horizons=[1,4]", "logger=none", "callbacks.timelines.num_clips=0"]
        runs[name] = train(make_cfg([*data, "trainer.max_epochs=1"], out=tmp_path / name))
    for key in (k for k in runs["near"] if "/cv/" in k):
        assert runs["far"][key] == pytest.approx(runs["near"][key], rel=1e-4), key
    out = tmp_path / "predicted"
    predict(make_cfg(["mode=predict", f"ckpt_path={tmp_path / 'far'}", "data=trajectories",
                      f"data.source.path={tmp_path / 'far.npz'}"], out=out))
    clips = np.load(out / "predictions" / "clips.npz")
    np.testing.assert_allclose(clips["positions"][0], far["positions"][0, 1:], rtol=0, atol=1e-3)
