"""Short real training runs of DNRI and DIDER on every real-data module (fixtures in the exact formats)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from dider.run import predict, train
from helpers import NO_SPARSITY
from helpers.fixtures import write_background, write_ind_root, write_trajectories, write_zhan

SMALL = ["experiment=smoke", "logger=none", "trainer.enable_progress_bar=false", *NO_SPARSITY,
         "model/net/decoder=recurrent", "data.loader.batch_size=4", "data.loader.eval_batch_size=4"]


@pytest.fixture(scope="module")
def roots(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("real")
    ind = write_ind_root(base / "ind", num_recordings=3, num_frames=600, num_tracks=5)
    write_background(ind, "02")  # the test recording with data.split=[1,1,1]
    write_zhan(base / "bball", num_train=24, num_test=8)
    write_trajectories(base / "traj.npz", num=30, steps=20, agents=4, mask=True)
    return {"ind": ind, "bball": base / "bball", "traj": base / "traj.npz"}


def data_overrides(name: str, roots: dict[str, Path]) -> list[str]:
    return {
        "ind": ["data=ind", f"data.source.root={roots['ind']}", "data.split=[1,1,1]", "data.num_train=8",
                "data.num_val=4", "data.num_test=4"],
        "basketball": ["data=basketball", f"data.source.root={roots['bball']}", "data.num_train=16", "data.num_val=4",
                       "data.num_test=4"],
        "trajectories": ["data=trajectories", f"data.source.path={roots['traj']}", "data.num_train=16",
                         "data.num_val=4",
                         "data.num_test=4", "protocol.horizons=[1,5]"],
    }[name]


RUNS = [(d, m) for m in ("dnri", "dider") for d in ("ind", "basketball", "trajectories")]


# RUNS, and on inD the other models whose segments restart where an edge enters
@pytest.mark.parametrize(("data", "model"), [*RUNS, ("ind", "dider_gate"), ("ind", "nri")])
def test_short_run(make_cfg, roots, tmp_path, data, model):
    cfg = make_cfg([f"model={model}", *SMALL, *data_overrides(data, roots),
                    f"model.num_edges={6 if model == 'dider' else 4}"], tiny=False, out=tmp_path / "run")
    metrics = train(cfg)
    mse = [v for k, v in metrics.items() if k.startswith("test/mse/h")]
    assert mse and all(v == v and v < float("inf") for v in mse), metrics  # finite, no NaN from empty frames
    assert not any(k.startswith("test/edge_acc") for k in metrics)  # no ground-truth edges here


def test_ind_command_line(roots, tmp_path, cache_dir, make_cfg):
    """The README's inD usage line (model=dider data=ind model.num_edges=6), on the inD fixture."""
    cmd = [sys.executable, "-m", "dider.run", "model=dider", "data=ind", "model.num_edges=6",
           f"data.source.root={roots['ind']}", f"hydra.run.dir={tmp_path}", f"data.cache_dir={cache_dir}",
           "data.split=[1,1,1]", "data.num_train=8", "data.num_val=4", "data.num_test=4", "trainer.max_epochs=1",
           "trainer.enable_progress_bar=false", "model.net.encoder.hidden=32", "model.net.decoder.hidden=32"]
    proc = subprocess.run(cmd, env={**os.environ, "HYDRA_FULL_ERROR": "1"}, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    record = json.loads((tmp_path / "metrics.json").read_text())
    assert record["config"]["model"]["num_edges"] == 6 and "test/mse/h01" in record["metrics"]
    # The consistency check: the fixture's two parked cars form one pair in every test window.
    m = record["metrics"]
    assert m["test/consistency/parked/edge_steps"] > 0 and 0.5 <= m["test/consistency/parked/share"] <= 1.0
    assert m["test/consistency/parked/type"] in range(6)
    figures = sorted(p.name for p in (tmp_path / "figures").glob("*.png"))
    assert "trajectories_00.png" in figures and "timeline_00.png" in figures

    # segments.json and clips.npz trace each test window back to the recording's rows
    clip = json.loads((tmp_path / "segments.json").read_text())["clips"][0]
    source = clip["source"]
    assert source["scene"] == 2 and source["frame"] % 10 == 0  # the test recording, 02; 25 Hz / 10
    edge = clip["edges"][0]
    assert (edge["sender_id"], edge["receiver_id"]) == (source["agent"][edge["sender"]],
                                                        source["agent"][edge["receiver"]])
    seg = edge["segments"][0]
    assert (seg["start_frame"], seg["end_frame"]) == (source["frame"] + 10 * seg["start"],
                                                      source["frame"] + 10 * seg["end"])
    tracks = pd.read_csv(roots["ind"] / "02_tracks.csv").set_index(["trackId", "frame"])
    with np.load(tmp_path / "clips.npz", allow_pickle=False) as z:
        assert z["clip"][0] == 0 and z["scene"][0] == 2 and z["agent"][0].tolist()[: len(source["agent"])] \
            == source["agent"]
        for slot, track in enumerate(source["agent"]):  # every agent of the window, at its first present step
            step = int(np.argmax(z["mask"][0, :, slot]))
            xy = tracks.loc[(track, source["frame"] + 10 * step), ["xCenter", "yCenter"]].to_numpy(float)
            assert np.allclose(z["positions"][0, step, slot], xy, atol=1e-3), (track, step)
        assert z["background_of"][0] == 0 and z["background_0"].ndim == 3 and z["background_0_extent"].shape == (4,)

    # mode=predict on every recording of the folder: rows name the recording, the tracks and their frames
    cfg = make_cfg(["mode=predict", f"ckpt_path={tmp_path / 'checkpoints' / 'last.ckpt'}", "data=ind",
                    f"data.source.root={roots['ind']}", "data.split=[1,1,1]", "logger=none"], tiny=False,
                   out=tmp_path / "predict")
    predict(cfg)
    table = pd.read_csv(tmp_path / "predict" / "predictions" / "segments.csv")
    assert set(table["scene"]) == {0, 1, 2}  # every recording, no split
    row = table.iloc[len(table) // 2]
    both = tracks_of(roots["ind"], int(row["scene"])).loc[[row["sender_id"], row["receiver_id"]]]
    frames = both.reset_index().groupby("trackId")["frame"]
    # both tracks exist at the segment's first frame and up to its last transition (10 frames per step)
    assert (frames.min() <= row["start_frame"]).all() and (frames.max() >= row["end_frame"] - 10).all()
    with np.load(tmp_path / "predict" / "predictions" / "clips.npz", allow_pickle=False) as z:
        assert z["background_of"].max() == 0 and (z["background_of"][z["scene"] == 2] == 0).all()


def tracks_of(root: Path, recording: int) -> pd.DataFrame:
    return pd.read_csv(root / f"{recording:02d}_tracks.csv").set_index(["trackId", "frame"])
