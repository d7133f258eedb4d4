"""trainer=ddp_sim: a real 2-process DDP run (gloo on CPU) whose test metrics and exported segments equal a
single-process evaluation of the same checkpoint."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from dider.run import predict, train
from helpers.fixtures import write_trajectories

# Deterministic evaluation: argmax edges in the roll-out; posterior types are argmaxes, so segments.json is
# deterministic too. 15 test clips: 8 on rank 0, 7 on rank 1, none counted twice.
COMMON = ["experiment=smoke", "model=dider", "model.net.rollout_edges=argmax", "data.num_test=15", "logger=none",
          "trainer.enable_progress_bar=false"]


def run_ddp(cmd: list[str], run_dir: Path) -> subprocess.CompletedProcess:
    """Run ``cmd`` (a 2-process ddp_spawn job writing ``run_dir``); once more, from an empty ``run_dir``, if
    a worker died of SIGABRT. Now and then a spawned gloo worker aborts (2 runs in about 22 here, in the
    predict job; 14 further runs did not reproduce it; Lightning's issue tracker reports the same
    intermittent SIGABRT in its own spawned DDP tests). A second failure in a row still fails the test."""
    for attempt in range(2):
        if attempt:
            shutil.rmtree(run_dir, ignore_errors=True)
        proc = subprocess.run(cmd, env={**os.environ, "HYDRA_FULL_ERROR": "1"}, capture_output=True, text=True,
                              timeout=600)
        if proc.returncode == 0 or "terminated with signal SIGABRT" not in proc.stderr:
            break
    return proc


@pytest.mark.slow  # three processes, about 45 s on a 2-core CPU: make test-all
def test_ddp_sim_matches_single_process_eval(make_cfg, tmp_path, cache_dir):
    run_dir = tmp_path / "ddp"
    proc = run_ddp([sys.executable, "-m", "dider.run", *COMMON, "trainer=ddp_sim", f"hydra.run.dir={run_dir}",
                    f"data.cache_dir={cache_dir}"], run_dir)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Starting with 2 processes" in proc.stderr + proc.stdout
    record = json.loads((run_dir / "metrics.json").read_text())
    ckpt = str(run_dir / record["checkpoint"])
    assert record["checkpoint"] and os.path.isfile(ckpt)

    single = train(make_cfg([*COMMON, "mode=eval", f"ckpt_path={ckpt}"], tiny=False, out=tmp_path / "eval"))
    for key in ("test/mse/h01", "test/mse/h15", "test/edge_acc/posterior/interaction", "test/edge_acc/posterior/none",
                "test/segments_per_edge"):
        assert record["metrics"][key] == pytest.approx(single[key], rel=1e-4), key
    ddp_segments = json.loads((run_dir / "segments.json").read_text())
    assert len(ddp_segments["clips"]) == 15
    assert ddp_segments == json.loads((tmp_path / "eval" / "segments.json").read_text())

    # mode=predict under DDP: each rank predicts every other clip; rank 0 writes them all, in input order
    new = write_trajectories(tmp_path / "new.npz", num=15, steps=12, agents=3, velocities=True, seed=3)
    args = ["mode=predict", f"ckpt_path={ckpt}", "data=trajectories", f"data.source.path={tmp_path / 'new.npz'}",
            "predict.forecast_steps=4", "experiment=smoke", "logger=none", "trainer.enable_progress_bar=false"]
    proc = run_ddp([sys.executable, "-m", "dider.run", *args, "trainer=ddp_sim",
                    f"hydra.run.dir={tmp_path / 'ddp_predict'}"], tmp_path / "ddp_predict")
    assert proc.returncode == 0, proc.stderr[-3000:]
    predict(make_cfg(args, tiny=False, out=tmp_path / "predict"))
    ddp_table = pd.read_csv(tmp_path / "ddp_predict" / "predictions" / "segments.csv")
    assert sorted(ddp_table["clip"].unique()) == list(range(len(new["positions"])))
    pd.testing.assert_frame_equal(ddp_table, pd.read_csv(tmp_path / "predict" / "predictions" / "segments.csv"))
    with np.load(tmp_path / "ddp_predict" / "predictions" / "clips.npz") as a, \
            np.load(tmp_path / "predict" / "predictions" / "clips.npz") as b:
        assert a["clip"].tolist() == list(range(15))
        for key in ("segments", "prior", "step_probs", "positions", "forecast"):
            np.testing.assert_allclose(a[key].astype(float), b[key].astype(float), atol=1e-5, err_msg=key)
