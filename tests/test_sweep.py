"""A real Hydra multirun through `python -m dider.run -m`."""

import json
import os
import subprocess
import sys


def test_multirun_two_jobs(tmp_path, cache_dir):
    env = {**os.environ, "HYDRA_FULL_ERROR": "1"}
    cmd = [sys.executable, "-m", "dider.run", "-m", f"hydra.sweep.dir={tmp_path}", f"data.cache_dir={cache_dir}",
           "experiment=smoke", "trainer.enable_progress_bar=false", "logger=csv", "seed=1,2"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    jobs = sorted(tmp_path.glob("*/metrics.json"))
    # jobs are named by their overrides (sweep.subdir = override_dirname)
    assert [p.parent.name for p in jobs] == ["seed=1", "seed=2"], jobs
    m1, m2 = (json.loads(p.read_text()) for p in jobs)
    assert m1["overrides"][-1] == "seed=1" and m2["seed"] == 2
    assert m1["metrics"]["test/mse/h01"] != m2["metrics"]["test/mse/h01"]
    assert (tmp_path / "multirun.yaml").exists()
