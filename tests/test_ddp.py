"""trainer=ddp_sim: a real 2-process DDP run (gloo on CPU) whose test metrics and exported segments equal a
single-process evaluation of the same checkpoint."""

import json
import os
import subprocess
import sys

import pytest

from dider.run import train

# Deterministic evaluation: argmax edges in the roll-out; posterior types are argmaxes, so segments.json is
# deterministic too. 15 test clips: 8 on rank 0, 7 on rank 1, none counted twice.
COMMON = ["experiment=smoke", "model=dider", "model.rollout_edges=argmax", "data.num_test=15", "logger=none",
          "trainer.enable_progress_bar=false"]


def test_ddp_sim_matches_single_process_eval(make_cfg, tmp_path, cache_dir):
    run_dir = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "dider.run", *COMMON, "trainer=ddp_sim", f"hydra.run.dir={run_dir}",
           f"data.cache_dir={cache_dir}"]
    proc = subprocess.run(cmd, env={**os.environ, "HYDRA_FULL_ERROR": "1"}, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Starting with 2 processes" in proc.stderr + proc.stdout
    record = json.loads((run_dir / "metrics.json").read_text())
    ckpt = record["checkpoint"]
    assert ckpt and os.path.isfile(ckpt)

    single = train(make_cfg([*COMMON, "mode=eval", f"ckpt_path={ckpt}"], tiny=False, out=tmp_path / "eval"))
    for key in ("test/mse/h01", "test/mse/h15", "test/edge_acc/posterior/interaction", "test/edge_acc/posterior/none",
                "test/segments_per_edge"):
        assert record["metrics"][key] == pytest.approx(single[key], rel=1e-4), key
    ddp_segments = json.loads((run_dir / "segments.json").read_text())
    assert len(ddp_segments["clips"]) == 15
    assert ddp_segments == json.loads((tmp_path / "eval" / "segments.json").read_text())
