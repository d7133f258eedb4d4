"""Timing a training or roll-out step, its matmul arithmetic, the device's matmul rate, and a
profile."""

from __future__ import annotations

import logging
import resource
import time
from collections.abc import Callable
from typing import Any

import torch
from hydra import compose, initialize_config_module
from omegaconf import DictConfig

from dider.bench.cases import GEMM_SHAPE, Case
from dider.bench.syncs import HostSyncs
from dider.models.vae import RelationalVAE
from dider.perf import compile_modules

log = logging.getLogger(__name__)


def build_model(overrides: list[str]) -> tuple[RelationalVAE, DictConfig]:
    """The network of a config, and the config's model node (for its burn-in)."""
    with initialize_config_module(version_base="1.3", config_module="dider.conf"):
        cfg = compose(config_name="config", overrides=overrides)
    return RelationalVAE.from_config(cfg.model), cfg.model


def train_step(
    model: Any, opt: torch.optim.Optimizer, batch: dict[str, torch.Tensor],
    autocast: str | None = None
) -> None:
    opt.zero_grad(set_to_none=True)
    device = batch["states"].device.type
    with torch.autocast(device, dtype=torch.bfloat16, enabled=autocast == "bf16"):
        loss = model.loss(model.infer(batch, hard=False))["loss"]
    loss.backward()
    opt.step()


def timed(fn: Callable[[], Any], iters: int, warmup: int, device: str) -> float:
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
    """Matmul arithmetic (GFLOP, multiply-add = 2) of one training step, counted on a throw-away
    copy."""
    from copy import deepcopy

    from torch.utils.flop_counter import FlopCounterMode

    model = deepcopy(model)
    with FlopCounterMode(display=False) as counter:
        train_step(model, torch.optim.SGD(model.parameters(), lr=0.0), batch, autocast)
    return counter.get_total_flops() / 1e9


GEMM_DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16}


def gemm_seconds(dtype: str, device: str, iters: int, warmup: int) -> float:
    """Seconds per matmul of :data:`GEMM_SHAPE` in ``dtype`` ("fp32" or "bf16") into a preallocated
    output."""
    m, k, n = GEMM_SHAPE
    a = torch.randn(m, k, device=device, dtype=GEMM_DTYPES[dtype])
    b = torch.randn(k, n, device=device, dtype=GEMM_DTYPES[dtype])
    out = torch.empty(m, n, device=device, dtype=GEMM_DTYPES[dtype])
    return timed(lambda: torch.mm(a, b, out=out), iters, warmup, device)


def gemm_case(case: Case, device: str) -> tuple[float, dict[str, Any]]:
    """The device's matmul rate on :data:`GEMM_SHAPE`, into a preallocated output (the compute
    ceiling)."""
    m, k, n = GEMM_SHAPE
    seconds = gemm_seconds(case.settings["dtype"], device, case.iters, case.warmup)
    return seconds, {"unit": "matmuls", "gflop_per_step": 2 * m * k * n / 1e9, "shape": [m, k, n]}


def random_batch(case: Case, device: str) -> dict[str, torch.Tensor]:
    states = torch.rand(case.batch, case.steps, case.agents, 4, device=device) * 2 - 1
    return {"states": states, "mask": torch.ones(states.shape[:3], dtype=torch.bool, device=device),
            "everyone": True}


def model_and_batch(case: Case, device: str) -> tuple[RelationalVAE, DictConfig,
                                                      dict[str, torch.Tensor]]:
    """The case's network on ``device`` (seeded), its model config and a random batch."""
    torch.manual_seed(0)
    model, model_cfg = build_model(case.overrides)
    return model.to(device), model_cfg, random_batch(case, device)


def model_case(case: Case, device: str) -> tuple[float, dict[str, Any]]:
    """A training step (forward, backward, Adam) or an evaluation roll-out on random clips."""
    model, model_cfg, batch = model_and_batch(case, device)
    extra: dict[str, Any] = {}
    if case.kind == "rollout":
        model.eval()
        burn_in = int(model_cfg.burn_in)

        def step() -> None:
            with torch.no_grad():
                model.rollout(batch["states"], batch["mask"], burn_in, case.steps - burn_in,
                              "global")

        return timed(step, case.iters, case.warmup, device), extra
    model.train()
    autocast = case.settings.get("autocast")
    # off for memory cases: the counting step would set the peak
    if case.settings.get("count_flops", True):
        extra["gflop_per_step"] = step_gflop(model, batch, autocast)
    if case.settings.get("compile"):
        compile_modules(model)
    opt = torch.optim.Adam(model.parameters(), lr=5e-4)
    # memory cases: the process's footprint before its step, to subtract
    if "checkpoint" in case.settings:
        before = (torch.cuda.max_memory_allocated() if device == "cuda"
                  else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
        extra["peak_before_step_mb"] = before / 2**20
    if case.settings.get("compile"):  # the first steps compile: report that cost on its own
        t0 = time.perf_counter()
        train_step(model, opt, batch, autocast)
        extra["compile_s"] = time.perf_counter() - t0
    seconds = timed(lambda: train_step(model, opt, batch, autocast), case.iters, case.warmup,
                    device)
    with HostSyncs() as syncs:  # after the timing: counting slows the step
        train_step(model, opt, batch, autocast)
    extra["host_syncs_per_step"] = syncs.total
    return seconds, extra


def profile_case(case: Case, device: str, rows: int = 25) -> str:
    """Where one training step of ``case`` spends its time: torch.profiler's op table (self time,
    the top ``rows`` ops) of one step after ``case.warmup`` untimed ones, with the model, batch and
    optimiser the case times."""
    from torch.profiler import ProfilerActivity, profile

    if case.kind != "train":
        raise ValueError(f"profile: {case.name} is a {case.kind} case; only training steps "
                         "(train/*) are profiled")
    model, _, batch = model_and_batch(case, device)
    model.train()
    if case.settings.get("compile"):
        compile_modules(model)
    opt = torch.optim.Adam(model.parameters(), lr=5e-4)
    autocast = case.settings.get("autocast")
    for _ in range(max(case.warmup, 1)):  # at least one: the first step allocates (and compiles)
        train_step(model, opt, batch, autocast)
    cuda = device == "cuda"
    with profile(activities=[ProfilerActivity.CPU,
                             *([ProfilerActivity.CUDA] if cuda else [])]) as prof:
        train_step(model, opt, batch, autocast)
        if cuda:
            torch.cuda.synchronize()
    return prof.key_averages().table(sort_by=f"self_{'cuda' if cuda else 'cpu'}_time_total",
                                     row_limit=rows)


# ----------------------------------------------------------- the reference implementation, same run
