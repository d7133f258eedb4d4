"""The data cases: generating the synthetic set, preprocessing an inD-size recording, loading batches,
and the end-of-run outputs of large scenes."""

from __future__ import annotations

import logging
import tempfile
import time
from pathlib import Path
from typing import Any

from dider.bench.cases import Case
from dider.bench.outputs import time_outputs
from dider.bench.steps import timed

log = logging.getLogger(__name__)


def benchmark_preprocess(tmpdir: str | Path | None = None, minutes: float = 20.0, num_tracks: int = 300,
                         num_parked: int = 20, seed: int = 0) -> float:
    """Seconds to read, validate, downsample and window one synthetic recording of ``minutes`` at 25 Hz
    with ``num_tracks`` tracks (the size of a real inD recording), with the default DNRI settings.

    Writing the CSV files is not timed. No assertion: a measurement to report.
    """
    from dider.bench.fake_levelx import write_levelx_recording
    from dider.data.levelx.reading import WindowParams
    from dider.data.levelx.recordings import discover_recordings
    from dider.data.levelx.windows import preprocess_recording

    with tempfile.TemporaryDirectory(dir=tmpdir) as tmp:
        frames = int(minutes * 60 * 25)
        # Moving road users stay 20 s to 2 min; parked vehicles the whole recording.
        write_levelx_recording(tmp, 0, num_frames=frames, num_tracks=num_tracks, num_parked=num_parked,
                               seed=seed, min_lifetime=25 * 20, max_lifetime=25 * 120)
        files = discover_recordings(Path(tmp))[0]
        log.info("benchmark: %s, %.0f MB", files.tracks.name, files.tracks.stat().st_size / 2**20)
        t0 = time.perf_counter()
        blob = preprocess_recording(files, WindowParams())
        seconds = time.perf_counter() - t0
        log.info("benchmark: %d tracks -> %d windows, %d agent rows in %.2f s", blob["num_tracks"],
                 len(blob["window_start"]), len(blob["states"]), seconds)
    return seconds


def data_case(case: Case, device: str, tmpdir: str | None) -> tuple[float, dict[str, Any]]:
    if case.kind == "generate":
        from dider.data.simulators.push import simulate_push

        return timed(lambda: simulate_push(case.batch, case.steps, seed=0), case.iters, case.warmup, device), {}
    if case.kind == "preprocess":
        return benchmark_preprocess(tmpdir, minutes=20.0, num_tracks=case.agents), {"unit": "recordings"}
    if case.kind == "outputs":
        record = time_outputs(case.agents, clips=case.batch, steps=case.steps, tmpdir=tmpdir)
        return record["seconds"]["total"] / case.batch, {"seconds": record["seconds"], "edges": record["edges"]}
    # load: one epoch of the synthetic training loader (2000 clips) with the given workers
    from dider.data.clips import ClipsDataModule
    from dider.data.simulators.push import Push

    with tempfile.TemporaryDirectory(dir=tmpdir) as cache:
        dm = ClipsDataModule(source=Push(), num_train=2000, num_val=16, num_test=16, cache_dir=cache,
                             loader={"batch_size": case.batch, "num_workers": case.settings["num_workers"],
                                     "pin_memory": device == "cuda"})
        dm.prepare_data()
        dm.setup()
        loader = dm.train_dataloader()
        t0 = time.perf_counter()
        clips = sum(b["states"].shape[0] for b in loader)
        seconds = time.perf_counter() - t0
    # peak memory of a load case is the main process's: the workers' own memory is not included
    return seconds * case.batch / clips, {"pin_memory": device == "cuda", "peak_memory": "main process only"}


