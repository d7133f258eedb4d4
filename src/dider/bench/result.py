"""Time to a result: the wall time of a whole documented job (``make demo``, the CPU-sized synthetic
table) beside the edge accuracy and forecast error it produced.

The job runs as its own ``python -m dider.run`` process, exactly as a user would start it, into a
throw-away folder; its ``metrics.json`` files are then read back through the report's reader.
``--quick`` shrinks the job to seconds (a check that the measurement works, not a measurement).

Used by ``python -m dider.bench --only result/demo`` (the cases ``result/*`` run only when named).
"""

from __future__ import annotations

import math
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dider.analysis.report import summarise

# What a record keeps of each model's metrics: edge recall (posterior and the online prior's) and
# the forecast error at the synthetic horizons.
RESULT_METRICS = ("test/edge_acc/posterior/none", "test/edge_acc/posterior/interaction",
                  "test/edge_acc/prior/interaction", "test/mse/h15", "test/mse/h25")

# Seconds-long versions of the jobs, for the test of the measurement itself.
QUICK = ["data.num_train=64", "data.num_val=16", "data.num_test=16", "data.loader.batch_size=16",
         "trainer.max_epochs=1", "model.net.encoder.hidden=32", "model.net.encoder.rnn_hidden=16",
         "model.net.decoder.hidden=32",
         "callbacks.timelines.num_clips=1"]


@dataclass(frozen=True)
class Job:
    name: str
    overrides: tuple[str, ...]
    sweep: bool  # a Hydra multirun (the experiment sets hydra.mode=MULTIRUN)


JOBS = {
    "result/demo": Job("result/demo", ("experiment=demo",), sweep=False),
    "result/synth_cpu_table": Job("result/synth_cpu_table", ("experiment=synth_cpu_table",),
                                  sweep=True),
}


def time_to_result(job: Job, quick: bool = False,
                   tmpdir: str | Path | None = None) -> dict[str, Any]:
    """Run ``job`` end to end and return its wall time and, per model, the mean of
    ``RESULT_METRICS`` over its runs (seeds). Raises ``RuntimeError`` with the job's last output
    when it fails."""
    with tempfile.TemporaryDirectory(dir=tmpdir) as tmp:
        folder = Path(tmp) / "job"
        where = f"hydra.sweep.dir={folder}" if job.sweep else f"hydra.run.dir={folder}"
        argv = [sys.executable, "-m", "dider.run", *job.overrides, where, *(QUICK if quick else [])]
        if job.sweep and quick:  # one seed of the sweep's models is enough to check the measurement
            argv.append("hydra.sweeper.params.seed=1")
        t0 = time.perf_counter()
        proc = subprocess.run(argv, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            tail = (proc.stdout + proc.stderr)[-2000:]
            raise RuntimeError(f"{' '.join(argv[2:])} failed with exit code "
                               f"{proc.returncode}:\n{tail}")
        summary = summarise(folder)
    models: dict[str, dict[str, float | int]] = {}
    for i, group in enumerate(summary.groups):
        values: dict[str, float | int] = {"runs": len(group.jobs)}
        for metric in RESULT_METRICS:
            if metric in summary.metrics and summary.stats.loc[i, (metric, "n")] > 0:
                values[metric] = float(summary.stats.loc[i, (metric, "mean")])
        models[group.label] = values
    failed = len(summary.failed) + len(summary.missing)
    return {"wall_s": wall, "command": "python -m dider.run " + " ".join(job.overrides),
            "quick": quick, "runs": sum(int(m["runs"]) for m in models.values()),
            "failed_runs": failed, "models": models, "complete": failed == 0
            and all(not math.isnan(float(v)) for m in models.values() for v in m.values())}
