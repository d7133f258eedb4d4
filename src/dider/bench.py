"""Benchmarks: throughput and peak memory, written as JSON records (and a scaling plot).

`python -m dider.bench --out bench/results.json [--only NAME ...] [--plot bench/scaling.png]`. Every case
runs in a fresh subprocess so its peak memory (ru_maxrss on CPU, max allocated on CUDA) is its own.

Cases: training steps of each model (Markovian and recurrent decoders, bf16, torch.compile), roll-out
(evaluation) throughput, generating the 40k synthetic clips, preprocessing an inD-size recording, loading
batches with DataLoader workers, and a training step as the agents (N) and the clip length (T) grow.

The roofline: every training record carries the step's matmul arithmetic (``gflop_per_step``, counted by
``torch.utils.flop_counter``) and the rate it achieved (``gflops``); the ``gemm/*`` cases measure the device's
matmul rate on the model's dominant shape. The summary divides the two into the most samples/s a step could
reach if it did nothing but its matmuls at that rate, and relates the measured rates to the public DNRI
implementation's (``dider.bench_summary.REFERENCE_SAMPLES_PER_S``).
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing as mp
import os
import platform
import resource
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from queue import Empty
from typing import Any

import torch
from hydra import compose, initialize_config_module
from omegaconf import DictConfig

from dider.bench_summary import plot, summary
from dider.io import atomic_write_text
from dider.models.vae import RelationalVAE
from dider.perf import compile_modules, tune_allocator

log = logging.getLogger(__name__)


@dataclass
class Case:
    name: str
    overrides: list[str]
    batch: int
    agents: int
    steps: int
    iters: int = 5
    warmup: int = 2
    settings: dict[str, Any] = field(default_factory=dict)
    kind: str = "train"  # train | rollout | generate | preprocess | load | gemm


# The encoder's edge-MLP matmul at batch 128, N = 3, T = 50: [B*T*E, 256] x [256, 256].
GEMM_SHAPE = (128 * 50 * 6, 256, 256)

SCALE_AGENTS = (3, 5, 10, 20, 50)
SCALE_STEPS = (50, 100, 200)
# The scaling series: DNRI's step with narrower networks (N = 50 has 2450 edges; full width would need
# tens of GB), so the growth in N and T shows, not the constant.
SCALE_MODEL = ["model=dnri", "model.encoder.hidden=64", "model.decoder.hidden=64", "model.sparsity_mix=0"]


def cases() -> list[Case]:
    recurrent = ["model/decoder=recurrent", "model.sparsity_mix=0"]
    out = [Case(f"gemm/{dtype}", [], 1, 0, 0, iters=20, warmup=3, kind="gemm", settings={"dtype": dtype})
           for dtype in ("fp32", "bf16")]
    for model in ("dnri", "dider", "dider_skid"):
        out.append(Case(f"train/{model}/synth", [f"model={model}"], 128, 3, 50))
        out.append(Case(f"train/{model}/recurrent", [f"model={model}", *recurrent], 128, 5, 40, iters=3))
    out.append(Case("train/dnri/recurrent/bf16", ["model=dnri", *recurrent], 128, 5, 40, iters=3,
                    settings={"autocast": "bf16"}))
    for model in ("dnri", "dider"):
        out.append(Case(f"train/{model}/synth/bf16", [f"model={model}"], 128, 3, 50, settings={"autocast": "bf16"}))
        out.append(Case(f"train/{model}/synth/compile", [f"model={model}"], 128, 3, 50, warmup=3,
                        settings={"compile": True}))
        out.append(Case(f"rollout/{model}/synth", [f"model={model}"], 256, 3, 50, kind="rollout"))
    out.append(Case("generate/synth/40k", [], 40000, 3, 50, iters=1, warmup=0, kind="generate"))
    out.append(Case("preprocess/ind/20min_300tracks", [], 1, 300, 30000, iters=1, warmup=0, kind="preprocess"))
    for workers in (0, 2):
        out.append(Case(f"load/synth/workers{workers}", [], 128, 3, 50, iters=1, warmup=0, kind="load",
                        settings={"num_workers": workers}))
    for n in SCALE_AGENTS:
        out.append(Case(f"scale/agents/N{n:02d}", SCALE_MODEL, 8, n, 50, iters=3, warmup=1))
    for t in SCALE_STEPS:
        out.append(Case(f"scale/steps/T{t:03d}", SCALE_MODEL, 8, 5, t, iters=3, warmup=1))
    return out


def build_model(overrides: list[str]) -> tuple[RelationalVAE, DictConfig]:
    """The network of a config, and the config's model node (for its burn-in)."""
    with initialize_config_module(version_base="1.3", config_module="dider.conf"):
        cfg = compose(config_name="config", overrides=overrides)
    return RelationalVAE.from_config(cfg.model), cfg.model


def _train_step(
    model: Any, opt: torch.optim.Optimizer, batch: dict[str, torch.Tensor], autocast: str | None = None
) -> None:
    opt.zero_grad(set_to_none=True)
    device = batch["states"].device.type
    with torch.autocast(device, dtype=torch.bfloat16, enabled=autocast == "bf16"):
        loss = model.loss(model.infer(batch, hard=False))["loss"]
    loss.backward()
    opt.step()


def _timed(fn: Callable[[], Any], iters: int, warmup: int, device: str) -> float:
    """Seconds per call of ``fn`` after ``warmup`` untimed calls (CUDA synchronised)."""
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    for _ in range(warmup):
        fn()
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    sync()
    start = time.perf_counter()
    for _ in range(iters):
        fn()
    sync()
    return (time.perf_counter() - start) / iters


def step_gflop(model: Any, batch: dict[str, torch.Tensor], autocast: str | None = None) -> float:
    """Matmul arithmetic (GFLOP, multiply-add = 2) of one training step, counted on a throw-away copy."""
    from copy import deepcopy

    from torch.utils.flop_counter import FlopCounterMode

    model = deepcopy(model)
    with FlopCounterMode(display=False) as counter:
        _train_step(model, torch.optim.SGD(model.parameters(), lr=0.0), batch, autocast)
    return counter.get_total_flops() / 1e9


def _gemm_case(case: Case, device: str) -> tuple[float, dict[str, Any]]:
    """The device's matmul rate on :data:`GEMM_SHAPE`, into a preallocated output (the compute ceiling)."""
    m, k, n = GEMM_SHAPE
    dtype = {"fp32": torch.float32, "bf16": torch.bfloat16}[case.settings["dtype"]]
    a, b = torch.randn(m, k, device=device, dtype=dtype), torch.randn(k, n, device=device, dtype=dtype)
    out = torch.empty(m, n, device=device, dtype=dtype)
    seconds = _timed(lambda: torch.mm(a, b, out=out), case.iters, case.warmup, device)
    gflop = 2 * m * k * n / 1e9
    return seconds, {"unit": "matmuls", "gflop_per_step": gflop, "shape": [m, k, n]}


def _random_batch(case: Case, device: str) -> dict[str, torch.Tensor]:
    states = torch.rand(case.batch, case.steps, case.agents, 4, device=device) * 2 - 1
    return {"states": states, "mask": torch.ones(states.shape[:3], dtype=torch.bool, device=device)}


def _model_case(case: Case, device: str) -> tuple[float, dict[str, Any]]:
    """A training step (forward, backward, Adam) or an evaluation roll-out on random clips."""
    torch.manual_seed(0)
    model, model_cfg = build_model(case.overrides)
    model = model.to(device)
    batch = _random_batch(case, device)
    extra: dict[str, Any] = {}
    if case.kind == "rollout":
        model.eval()
        burn_in = int(model_cfg.burn_in)

        def step() -> None:
            with torch.no_grad():
                model.rollout(batch["states"], batch["mask"], burn_in, case.steps - burn_in, "global")

        return _timed(step, case.iters, case.warmup, device), extra
    model.train()
    autocast = case.settings.get("autocast")
    extra["gflop_per_step"] = step_gflop(model, batch, autocast)
    if case.settings.get("compile"):
        compile_modules(model)
    opt = torch.optim.Adam(model.parameters(), lr=5e-4)
    if case.settings.get("compile"):  # the first steps compile: report that cost on its own
        t0 = time.perf_counter()
        _train_step(model, opt, batch, autocast)
        extra["compile_s"] = time.perf_counter() - t0
    return _timed(lambda: _train_step(model, opt, batch, autocast), case.iters, case.warmup, device), extra


def benchmark_preprocess(tmpdir: str | Path | None = None, minutes: float = 20.0, num_tracks: int = 300,
                         num_parked: int = 20, seed: int = 0) -> float:
    """Seconds to read, validate, downsample and window one synthetic recording of ``minutes`` at 25 Hz
    with ``num_tracks`` tracks (the size of a real inD recording), with the default DNRI settings.

    Writing the CSV files is not timed. No assertion: a measurement to report.
    """
    from dider.data.fakes import write_levelx_recording
    from dider.data.levelx.recordings import discover_recordings
    from dider.data.levelx.windows import WindowParams, preprocess_recording

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


def _data_case(case: Case, device: str, tmpdir: str | None) -> tuple[float, dict[str, Any]]:
    if case.kind == "generate":
        from dider.data.simulate import simulate_push

        return _timed(lambda: simulate_push(case.batch, case.steps, seed=0), case.iters, case.warmup, device), {}
    if case.kind == "preprocess":
        return benchmark_preprocess(tmpdir, minutes=20.0, num_tracks=case.agents), {"unit": "recordings"}
    # load: one epoch of the synthetic training loader (2000 clips) with the given workers
    from dider.data.synth import SynthDataModule

    with tempfile.TemporaryDirectory(dir=tmpdir) as cache:
        dm = SynthDataModule(num_train=2000, num_val=16, num_test=16, batch_size=case.batch, cache_dir=cache,
                             num_workers=case.settings["num_workers"], pin_memory=device == "cuda")
        dm.prepare_data()
        dm.setup()
        loader = dm.train_dataloader()
        t0 = time.perf_counter()
        clips = sum(b["states"].shape[0] for b in loader)
        seconds = time.perf_counter() - t0
    # peak memory of a load case is the main process's: the workers' own memory is not included
    return seconds * case.batch / clips, {"pin_memory": device == "cuda", "peak_memory": "main process only"}


def run_case(case: Case, device: str, tmpdir: str | None = None) -> dict[str, Any]:
    if case.kind in ("train", "rollout"):
        step_s, extra = _model_case(case, device)
    elif case.kind == "gemm":
        step_s, extra = _gemm_case(case, device)
    else:
        step_s, extra = _data_case(case, device, tmpdir)
    peak = (torch.cuda.max_memory_allocated() if device == "cuda" and case.kind in ("train", "rollout")
            else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
    rate = {"gflops": extra["gflop_per_step"] / step_s} if "gflop_per_step" in extra else {}
    return {
        "name": case.name, "kind": case.kind, "samples_per_s": case.batch / step_s, "step_s": step_s, **rate,
        "peak_memory_mb": peak / 2**20, "device": device, "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "settings": {"batch": case.batch, "agents": case.agents, "steps": case.steps, "iters": case.iters,
                     "overrides": case.overrides, **case.settings, **extra},
    }  # fmt: skip


def _worker(case: Case, device: str, queue: mp.Queue) -> None:
    tune_allocator()
    try:
        queue.put(run_case(case, device))
    except Exception as e:  # noqa: BLE001 - a failed case is reported as such and the others still run
        queue.put({"name": case.name, "kind": case.kind, "error": f"{type(e).__name__}: {e}"})


def _run_isolated(case: Case, device: str) -> dict[str, Any]:
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_worker, args=(case, device, queue))
    proc.start()
    while True:
        try:
            record = queue.get(timeout=5)
            break
        except Empty:
            if not proc.is_alive():  # killed (e.g. out of memory) before it could report
                record = {"name": case.name, "kind": case.kind, "error": f"worker exited with code {proc.exitcode}"}
                break
    proc.join()
    return record


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("bench/results.json"))
    parser.add_argument("--plot", type=Path, default=None, help="scaling plot (default: next to --out)")
    parser.add_argument("--only", nargs="*", help="run only the cases whose name contains one of these")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args(argv)
    meta = {"machine": platform.processor() or platform.machine(), "python": platform.python_version(),
            "cpus": os.cpu_count(), "gpu": torch.cuda.get_device_name() if args.device == "cuda" else None}
    records: list[dict[str, Any]] = []
    for case in cases():
        if args.only and not any(s in case.name for s in args.only):
            continue
        record = _run_isolated(case, args.device)
        records.append(record)
        if "error" in record:
            print(f"{record['name']:<32} FAILED: {record['error']}", flush=True)
        else:
            print(f"{record['name']:<32} {record['samples_per_s']:11.1f} samples/s  "
                  f"{record['step_s'] * 1000:9.1f} ms/step  peak {record['peak_memory_mb']:.0f} MiB", flush=True)
        # Written after every case: an interrupted benchmark keeps what it measured.
        atomic_write_text(args.out, json.dumps({"meta": meta, "summary": summary(records), "records": records},
                                               indent=2))
    derived = summary(records)
    for key, value in derived.items():
        print(f"{key:<44} {value:.2f}")
    if any(r["name"].startswith("scale/") for r in records):
        plot(records, args.plot or args.out.with_suffix(".png"))
    print(f"wrote {args.out}")
    return records


def cli() -> None:
    """The console script (``dider-bench``): ``main`` without its return value (an exit status of 0)."""
    main()


if __name__ == "__main__":
    main()
