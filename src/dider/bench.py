"""Benchmarks: training throughput and peak memory, written as JSON records.

`python -m dider.bench --out bench/results.json [--only NAME ...]`. Every case runs in a fresh
subprocess so its peak memory (ru_maxrss on CPU, max allocated on CUDA) is its own.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import platform
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from dider.data.cache import atomic_write_text
from dider.perf import tune_allocator


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


def cases() -> list[Case]:
    recurrent = ["model/decoder=recurrent", "model.sparsity_mix=0"]
    out = []
    for model in ("dnri", "dider", "dider_skid"):
        out.append(Case(f"train/{model}/synth", [f"model={model}"], 128, 3, 50))
        out.append(Case(f"train/{model}/recurrent", [f"model={model}", *recurrent], 128, 5, 40, iters=3))
    for model in ("dnri", "dider"):
        out.append(Case(f"train/{model}/synth/bf16", [f"model={model}"], 128, 3, 50, settings={"autocast": "bf16"}))
    return out


def build_model(overrides: list[str]) -> torch.nn.Module:
    with initialize_config_module(version_base="1.3", config_module="dider.conf"):
        cfg = compose(config_name="config", overrides=overrides)
    return instantiate(cfg.model, _convert_="all")


def _train_step(
    model: Any, opt: torch.optim.Optimizer, batch: dict[str, torch.Tensor], autocast: str | None = None
) -> None:
    opt.zero_grad(set_to_none=True)
    device = batch["states"].device.type
    with torch.autocast(device, dtype=torch.bfloat16, enabled=autocast == "bf16"):
        loss = model.loss(model.infer(batch, hard=False))["loss"]
    loss.backward()
    opt.step()


def run_case(case: Case, device: str) -> dict[str, Any]:
    torch.manual_seed(0)
    model = build_model(case.overrides).to(device).train()
    opt = torch.optim.Adam(model.parameters(), lr=5e-4)
    states = torch.rand(case.batch, case.steps, case.agents, 4, device=device) * 2 - 1
    batch = {"states": states, "mask": torch.ones(states.shape[:3], dtype=torch.bool, device=device)}
    autocast = case.settings.get("autocast")
    for _ in range(case.warmup):
        _train_step(model, opt, batch, autocast)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    sync()
    start = time.perf_counter()
    for _ in range(case.iters):
        _train_step(model, opt, batch, autocast)
    sync()
    step_s = (time.perf_counter() - start) / case.iters
    peak = (torch.cuda.max_memory_allocated() if device == "cuda"
            else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
    return {
        "name": case.name, "samples_per_s": case.batch / step_s, "step_s": step_s, "peak_memory_mb": peak / 2**20,
        "device": device, "threads": torch.get_num_threads(), "torch": torch.__version__,
        "settings": {"batch": case.batch, "agents": case.agents, "steps": case.steps, "iters": case.iters,
                     "overrides": case.overrides, **case.settings},
    }  # fmt: skip


def _worker(case: Case, device: str, queue: mp.Queue) -> None:
    tune_allocator()
    queue.put(run_case(case, device))


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("bench/results.json"))
    parser.add_argument("--only", nargs="*", help="run only the cases whose name contains one of these")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args(argv)
    ctx = mp.get_context("spawn")
    records = []
    for case in cases():
        if args.only and not any(s in case.name for s in args.only):
            continue
        queue = ctx.Queue()
        proc = ctx.Process(target=_worker, args=(case, args.device, queue))
        proc.start()
        record = queue.get()
        proc.join()
        records.append(record)
        print(f"{record['name']:<32} {record['samples_per_s']:9.1f} samples/s  "
              f"{record['step_s'] * 1000:8.1f} ms/step  peak {record['peak_memory_mb']:.0f} MiB", flush=True)
    meta = {"machine": platform.processor() or platform.machine(), "python": platform.python_version()}
    atomic_write_text(args.out, json.dumps({"meta": meta, "records": records}, indent=2))
    print(f"wrote {args.out}")
    return records


if __name__ == "__main__":
    main()
