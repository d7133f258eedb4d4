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

The reference in the same run: ``--reference PATH`` (a checkout of cgraber/cvpr_dNRI, imported from PATH) also
times the public DNRI code's training step against ours on the same random batch, in one process, in alternating
rounds (:func:`compare_with_reference`). The results JSON then has a ``reference`` section and the summary's
speed-ups come from it instead of ``REFERENCE_SAMPLES_PER_S``. ``--reference-size tiny`` runs the same at toy
sizes (a check that it works, not a measurement). The ``memory/*`` cases record the peak memory of one DNRI
training step at the paper's widths as N grows, with the activation checkpointing of the encoder and the
decoder off and on, and ``memory/dnri/largest_N/*`` searches for the largest N whose step fits
``--memory-limit-gb`` (:mod:`dider.bench_memory`). The ``result/*`` cases time a whole documented job, ``make
demo``'s or the CPU-sized synthetic table, beside the edge accuracy it produced (:mod:`dider.bench_result`);
they run only when ``--only`` names them. ``--profile CASE`` times nothing: it prints and writes where one step of a
training case spends its time (torch.profiler's op table, :func:`profile_case`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import multiprocessing as mp
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from queue import Empty
from typing import Any

import torch
from hydra import compose, initialize_config_module
from omegaconf import DictConfig
from torch import nn

from dider.bench_memory import largest_agents
from dider.bench_outputs import time_outputs
from dider.bench_result import JOBS, time_to_result
from dider.bench_summary import plot, summary
from dider.io import atomic_write_text
from dider.models.vae import RelationalVAE
from dider.perf import ALLOCATORS, allocator_mode, compile_modules, native_bf16, tune_allocator

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
    kind: str = "train"  # train | rollout | generate | preprocess | load | outputs | gemm | largest | result


# The encoder's edge-MLP matmul at batch 128, N = 3, T = 50: [B*T*E, 256] x [256, 256].
GEMM_SHAPE = (128 * 50 * 6, 256, 256)

SCALE_AGENTS = (3, 5, 10, 20, 50)
OUTPUT_AGENTS = (40, 100)
SCALE_STEPS = (50, 100, 200)
# The scaling series: DNRI's step with narrower networks (N = 50 has 2450 edges; full width would need
# tens of GB), so the growth in N and T shows, not the constant.
SCALE_MODEL = ["model=dnri", "model.encoder.hidden=64", "model.decoder.hidden=64", "model.sparsity_mix=0"]


# Peak memory of one DNRI step at the paper's widths (batch 8), activation checkpointing off and on.
MEMORY_AGENTS = (10, 20, 30)
CHECKPOINTING = ["model.encoder.checkpoint=true", "model.decoder.checkpoint=true"]


def memory_case(agents: int, checkpoint: bool) -> Case:
    """One DNRI training step at the paper's widths, batch 8, T 50: its peak is the figure."""
    return Case(f"memory/dnri/N{agents:02d}/checkpoint_{'on' if checkpoint else 'off'}",
                ["model=dnri", *(CHECKPOINTING if checkpoint else [])], 8, agents, 50, iters=1, warmup=0,
                settings={"count_flops": False, "checkpoint": checkpoint})


def _machine_memory_mb(device: str) -> float:
    if device == "cuda":
        return torch.cuda.get_device_properties(0).total_memory / 2**20
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**20


def largest_case(case: Case, records: list[dict[str, Any]], device: str, limit_gb: float) -> dict[str, Any]:
    """The largest N whose training step peaks within ``limit_gb`` (:func:`dider.bench_memory.largest_agents`),
    starting from this run's fixed-N memory records of the same setting."""
    checkpoint = bool(case.settings["checkpoint"])
    saver = "on" if checkpoint else "off"
    start = {r["settings"]["agents"]: r["peak_memory_mb"] for r in records
             if r["name"].startswith("memory/dnri/N") and r["name"].endswith(saver) and "error" not in r}

    def probe(n: int) -> float:
        record = _run_isolated(memory_case(n, checkpoint), device)
        print(f"    N = {n}: " + (f"peak {record['peak_memory_mb']:.0f} MiB" if "error" not in record
                                  else f"FAILED: {record['error']}"), flush=True)
        return float("inf") if "error" in record else record["peak_memory_mb"]  # killed: did not fit

    t0 = time.perf_counter()
    found = largest_agents(probe, limit_gb * 1024, 0.85 * _machine_memory_mb(device), start)
    return {"name": case.name, "kind": case.kind, "device": device, "torch": torch.__version__,
            "limit_gb": limit_gb, "search_s": time.perf_counter() - t0, **found,
            "settings": {"batch": case.batch, "steps": case.steps, "overrides": ["model=dnri"]
                         + (CHECKPOINTING if checkpoint else []), "checkpoint": checkpoint}}


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
    for n in OUTPUT_AGENTS:  # the end-of-run outputs of a test set of 64 clips (step_s: all of them)
        out.append(Case(f"outputs/N{n:03d}", [], 64, n, 50, iters=1, warmup=0, kind="outputs"))
    for n in SCALE_AGENTS:
        out.append(Case(f"scale/agents/N{n:02d}", SCALE_MODEL, 8, n, 50, iters=3, warmup=1))
    for t in SCALE_STEPS:
        out.append(Case(f"scale/steps/T{t:03d}", SCALE_MODEL, 8, 5, t, iters=3, warmup=1))
    for n in MEMORY_AGENTS:  # one step each: the peak is the figure (N = 30 takes about 40 s on 2 cores)
        for saver in ("off", "on"):
            out.append(memory_case(n, saver == "on"))
    for saver in ("off", "on"):  # after the fixed N above, whose peaks start the search
        out.append(Case(f"memory/dnri/largest_N/checkpoint_{saver}", [], 8, 0, 50, iters=1, warmup=0,
                        kind="largest", settings={"checkpoint": saver == "on"}))
    out += [Case(name, [], 0, 0, 0, iters=1, warmup=0, kind="result") for name in JOBS]
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


GEMM_DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16}


def _gemm_seconds(dtype: str, device: str, iters: int, warmup: int) -> float:
    """Seconds per matmul of :data:`GEMM_SHAPE` in ``dtype`` ("fp32" or "bf16") into a preallocated output."""
    m, k, n = GEMM_SHAPE
    a = torch.randn(m, k, device=device, dtype=GEMM_DTYPES[dtype])
    b = torch.randn(k, n, device=device, dtype=GEMM_DTYPES[dtype])
    out = torch.empty(m, n, device=device, dtype=GEMM_DTYPES[dtype])
    return _timed(lambda: torch.mm(a, b, out=out), iters, warmup, device)


def _gemm_case(case: Case, device: str) -> tuple[float, dict[str, Any]]:
    """The device's matmul rate on :data:`GEMM_SHAPE`, into a preallocated output (the compute ceiling)."""
    m, k, n = GEMM_SHAPE
    seconds = _gemm_seconds(case.settings["dtype"], device, case.iters, case.warmup)
    return seconds, {"unit": "matmuls", "gflop_per_step": 2 * m * k * n / 1e9, "shape": [m, k, n]}


def _random_batch(case: Case, device: str) -> dict[str, torch.Tensor]:
    states = torch.rand(case.batch, case.steps, case.agents, 4, device=device) * 2 - 1
    return {"states": states, "mask": torch.ones(states.shape[:3], dtype=torch.bool, device=device)}


def _model_and_batch(case: Case, device: str) -> tuple[RelationalVAE, DictConfig, dict[str, torch.Tensor]]:
    """The case's network on ``device`` (seeded), its model config and a random batch."""
    torch.manual_seed(0)
    model, model_cfg = build_model(case.overrides)
    return model.to(device), model_cfg, _random_batch(case, device)


def _model_case(case: Case, device: str) -> tuple[float, dict[str, Any]]:
    """A training step (forward, backward, Adam) or an evaluation roll-out on random clips."""
    model, model_cfg, batch = _model_and_batch(case, device)
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
    if case.settings.get("count_flops", True):  # off for memory cases: the counting step would set the peak
        extra["gflop_per_step"] = step_gflop(model, batch, autocast)
    if case.settings.get("compile"):
        compile_modules(model)
    opt = torch.optim.Adam(model.parameters(), lr=5e-4)
    if "checkpoint" in case.settings:  # memory cases: the process's footprint before its step, to subtract
        before = (torch.cuda.max_memory_allocated() if device == "cuda"
                  else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
        extra["peak_before_step_mb"] = before / 2**20
    if case.settings.get("compile"):  # the first steps compile: report that cost on its own
        t0 = time.perf_counter()
        _train_step(model, opt, batch, autocast)
        extra["compile_s"] = time.perf_counter() - t0
    return _timed(lambda: _train_step(model, opt, batch, autocast), case.iters, case.warmup, device), extra


def profile_case(case: Case, device: str, rows: int = 25) -> str:
    """Where one training step of ``case`` spends its time: torch.profiler's op table (self time, the top
    ``rows`` ops) of one step after ``case.warmup`` untimed ones, with the model, batch and optimiser the case
    times."""
    from torch.profiler import ProfilerActivity, profile

    if case.kind != "train":
        raise ValueError(f"profile: {case.name} is a {case.kind} case; only training steps (train/*) are profiled")
    model, _, batch = _model_and_batch(case, device)
    model.train()
    if case.settings.get("compile"):
        compile_modules(model)
    opt = torch.optim.Adam(model.parameters(), lr=5e-4)
    autocast = case.settings.get("autocast")
    for _ in range(max(case.warmup, 1)):  # at least one: the first step allocates (and compiles)
        _train_step(model, opt, batch, autocast)
    cuda = device == "cuda"
    with profile(activities=[ProfilerActivity.CPU, *([ProfilerActivity.CUDA] if cuda else [])]) as prof:
        _train_step(model, opt, batch, autocast)
        if cuda:
            torch.cuda.synchronize()
    return prof.key_averages().table(sort_by=f"self_{'cuda' if cuda else 'cpu'}_time_total", row_limit=rows)


# ------------------------------------------------------------------ the reference implementation, same run
REFERENCE_CASES = ("train/dnri/synth", "train/dnri/recurrent")
# --reference-size: "full" is the benchmark's cases as they are; "tiny" shrinks batch, clip and widths so the
# comparison runs in seconds (a test of the machinery; its timings mean nothing).
REFERENCE_SIZES: dict[str, dict[str, Any]] = {
    "full": {},
    "tiny": {"batch": 4, "steps": 8, "overrides": [
        "model.encoder.hidden=16", "model.encoder.rnn_hidden=8", "model.encoder.head_hidden=8",
        "model.prior.hidden=8", "model.decoder.hidden=16"]},
}  # fmt: skip
# What the reference's decoder_type is for each of our decoder classes.
REFERENCE_DECODERS = {"MarkovDecoder": "ref_mlp", "RecurrentDecoder": "recurrent"}


def reference_params(model_cfg: DictConfig, num_agents: int, device: str) -> dict[str, Any]:
    """The public DNRI code's ``params`` dict for the network of our model config ``model_cfg`` (``model=dnri``
    with either decoder): the same widths and depths, teacher-forced training with soft Gumbel-softmax edges,
    normalised Gaussian NLL and KL, and our ``sparsity_mix`` 0.5 as its ``add_uniform_prior`` (a fixed
    0.5/0.5 mix with KL(mean q || [no_edge_prob, ...]))."""
    enc, dec, prior = model_cfg.encoder, model_cfg.decoder, model_cfg.prior
    decoder_class = str(dec._target_).rsplit(".", 1)[-1]
    if decoder_class not in REFERENCE_DECODERS or model_cfg.sparsity_mix not in (0, 0.5):
        raise ValueError(f"no reference counterpart of decoder {decoder_class}, sparsity_mix={model_cfg.sparsity_mix}")
    return {
        "num_vars": num_agents, "input_size": enc.input_dim, "num_edge_types": model_cfg.num_edges,
        "skip_first": dec.skip_first, "gpu": device == "cuda",
        "encoder_hidden": enc.hidden, "encoder_rnn_hidden": enc.rnn_hidden, "encoder_rnn_type": "lstm",
        "encoder_mlp_num_layers": enc.head_layers, "encoder_mlp_hidden": enc.head_hidden,
        "encoder_dropout": enc.dropout, "prior_num_layers": prior.num_layers, "prior_hidden_size": prior.hidden,
        "decoder_type": REFERENCE_DECODERS[decoder_class], "decoder_hidden": dec.hidden,
        "decoder_dropout": dec.dropout, "gumbel_temp": model_cfg.gumbel_tau, "train_hard_sample": False,
        "teacher_forcing_steps": -1, "val_teacher_forcing_steps": -1, "normalize_kl": True, "normalize_nll": True,
        "nll_loss_type": "gaussian", "prior_variance": model_cfg.nll_variance, "kl_coef": 1.0,
        "add_uniform_prior": model_cfg.sparsity_mix > 0, "no_edge_prior": model_cfg.no_edge_prob,
    }  # fmt: skip


def interleaved_timing(
    steps: Mapping[str, Callable[[], Any]],
    rounds: int,
    iters: int,
    warmup: int,
    device: str = "cpu",
    clock: Callable[[], float] = time.perf_counter,
) -> dict[str, list[float]]:
    """Seconds per call of each function, one value per round: ``warmup`` untimed calls of each, then
    ``rounds`` rounds of ``iters`` timed calls of each in turn. The order rotates by one every round, so no
    function always runs first (or right after the same neighbour) and a slow spell of the machine falls on
    all of them alike. -> {name: [s/call of round 0, round 1, ...]}."""
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    names = list(steps)
    for name in names:
        for _ in range(warmup):
            steps[name]()
    out: dict[str, list[float]] = {name: [] for name in names}
    for r in range(rounds):
        k = r % len(names)
        for name in names[k:] + names[:k]:
            sync()
            start = clock()
            for _ in range(iters):
                steps[name]()
            sync()
            out[name].append((clock() - start) / iters)
    return out


def speedups(per_round: Mapping[str, list[float]], baseline: str) -> dict[str, Any]:
    """From :func:`interleaved_timing`'s rounds: each function's median s/call, and every other function's
    speed-up over ``baseline`` (baseline time / its time) per round, paired within the round, and their median
    (the headline: a pairing within rounds cancels the machine's slow drifts)."""
    out: dict[str, Any] = {"step_s": {k: statistics.median(v) for k, v in per_round.items()},
                           "step_s_per_round": {k: list(v) for k, v in per_round.items()},
                           "speedup": {}, "speedup_per_round": {}}
    for name, times in per_round.items():
        if name != baseline:
            ratios = [b / t for b, t in zip(per_round[baseline], times, strict=True)]
            out["speedup_per_round"][name] = ratios
            out["speedup"][name] = statistics.median(ratios)
    return out


def _reference_step(ref: nn.Module, opt: torch.optim.Optimizer, x: torch.Tensor) -> None:
    """The reference's training step as its training script takes it (without gradient clipping, like ours).
    x: [B, T, N, D]."""
    loss = ref.calculate_loss(x, is_train=True, return_logits=True)[0]
    loss.backward()
    opt.step()
    opt.zero_grad()


@contextlib.contextmanager
def _reference_on_path(checkout: Path) -> Any:
    """The checkout's ``dnri`` package importable for the duration."""
    sys.path.insert(0, str(checkout))
    try:
        yield
    finally:
        sys.path.remove(str(checkout))


def _checkout_commit(checkout: Path) -> str | None:
    try:
        proc = subprocess.run(["git", "-C", str(checkout), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, timeout=10, check=False)
    except OSError:
        return None
    return proc.stdout.strip() or None


def compare_with_reference(
    checkout: Path,
    names: tuple[str, ...] = REFERENCE_CASES,
    size: str = "full",
    rounds: int = 4,
    iters: int = 2,
    warmup: int = 1,
    device: str = "cpu",
    threads: int | None = None,
    bf16: bool = True,
) -> dict[str, Any]:
    """Time the public DNRI code's training step and ours on the same random clips, in this one process.

    For each case of ``names`` (:func:`cases`' settings, shrunk by ``size``): the reference step is its training
    script's (``calculate_loss(inputs, is_train=True)``'s loss, backward, an Adam step, zero_grad); ours is
    :func:`_train_step` in fp32 and in bf16 autocast; both with Adam at lr 5e-4. The three alternate in rounds
    (:func:`interleaved_timing`). -> the results JSON's ``reference`` section: per case the batch, N, T, the
    median s/step of ``reference``, ``fp32`` and ``bf16`` with every round's value, and the speed-ups
    (reference time / ours) with every round's value; the torch version and thread count (``threads``: set
    it first; None keeps torch's default). ``bf16=False`` leaves ours in bf16 out (a device that emulates it
    would take most of the run)."""
    if threads is not None:
        torch.set_num_threads(threads)
    checkout = Path(checkout).resolve()
    if not (checkout / "dnri" / "models" / "dnri.py").is_file():
        raise FileNotFoundError(f"{checkout}: not a checkout of cgraber/cvpr_dNRI (no dnri/models/dnri.py)")
    scale = REFERENCE_SIZES[size]
    by_name = {c.name: c for c in cases()}
    out: dict[str, Any] = {}
    with _reference_on_path(checkout):
        from dnri.models.dnri import DNRI  # the reference, imported from the checkout

        for name in names:
            case = by_name[name]
            batch_size, steps = scale.get("batch", case.batch), scale.get("steps", case.steps)
            torch.manual_seed(0)
            ours, model_cfg = build_model([*case.overrides, *scale.get("overrides", [])])
            ours = ours.to(device).train()
            params = reference_params(model_cfg, case.agents, device)
            with contextlib.redirect_stdout(sys.stderr):  # it prints its prior on construction
                ref = DNRI(params).to(device).train()
            batch = _random_batch(Case(name, [], batch_size, case.agents, steps), device)
            opt_ref = torch.optim.Adam([p for p in ref.parameters() if p.requires_grad], lr=5e-4)
            opt_ours = torch.optim.Adam(ours.parameters(), lr=5e-4)

            fns: dict[str, Callable[[], Any]] = {
                "reference": lambda m=ref, o=opt_ref, x=batch["states"]: _reference_step(m, o, x),
                "fp32": lambda m=ours, o=opt_ours, b=batch: _train_step(m, o, b),
            }
            if bf16:
                fns["bf16"] = lambda m=ours, o=opt_ours, b=batch: _train_step(m, o, b, "bf16")
            timing = speedups(interleaved_timing(fns, rounds, iters, warmup, device), "reference")
            timing["ceiling"] = matmul_ceiling(ours, batch, timing["step_s"]["reference"], list(fns)[1:], device)
            out[name] = {
                "batch": batch_size, "agents": case.agents, "steps": steps, "size": size,
                "overrides": [*case.overrides, *scale.get("overrides", [])], "reference_params": params,
                "rounds": rounds, "iters": iters, "warmup": warmup,
                "samples_per_s": {k: batch_size / v for k, v in timing["step_s"].items()}, **timing,
                "device": device, "threads": torch.get_num_threads(), "torch": torch.__version__,
            }  # fmt: skip
    return {"checkout": str(checkout), "commit": _checkout_commit(checkout), "cases": out}


def matmul_ceiling(model: Any, batch: dict[str, torch.Tensor], reference_s: float, dtypes: list[str],
                   device: str, iters: int = 10) -> dict[str, Any]:
    """The speed-up over the reference that a step of our arithmetic would reach if it did nothing but its
    matrix products at this device's matmul rate (:data:`GEMM_SHAPE`, timed here, in this process), per
    dtype of ``dtypes``: reference_s / (GFLOP per step / GFLOP/s). A target above it cannot be met on the
    device by any implementation of this arithmetic. -> ``gflop_per_step``, ``gemm_gflop_per_s`` and
    ``speedup`` by dtype."""
    m, k, n = GEMM_SHAPE
    gflop = step_gflop(model, batch)
    rate = {d: 2 * m * k * n / 1e9 / _gemm_seconds(d, device, iters, 2) for d in dtypes}
    return {"gflop_per_step": gflop, "gemm_gflop_per_s": rate,
            "speedup": {d: reference_s / (gflop / r) for d, r in rate.items()}}


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
    if case.kind == "outputs":
        record = time_outputs(case.agents, clips=case.batch, steps=case.steps, tmpdir=tmpdir)
        return record["seconds"]["total"] / case.batch, {"seconds": record["seconds"], "edges": record["edges"]}
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


def _worker(fn: Callable[..., dict[str, Any]], args: tuple[Any, ...], failed: dict[str, Any], queue: mp.Queue) -> None:
    tune_allocator()
    try:
        queue.put(fn(*args))
    except Exception as e:  # noqa: BLE001 - a failed case is reported as such and the others still run
        queue.put({**failed, "error": f"{type(e).__name__}: {e}"})


def _isolated(fn: Callable[..., dict[str, Any]], args: tuple[Any, ...], failed: dict[str, Any]) -> dict[str, Any]:
    """``fn(*args)`` in a fresh subprocess; on failure ``failed`` with an ``error``."""
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_worker, args=(fn, args, failed, queue))
    proc.start()
    while True:
        try:
            record = queue.get(timeout=5)
            break
        except Empty:
            if not proc.is_alive():  # killed (e.g. out of memory) before it could report
                record = {**failed, "error": f"worker exited with code {proc.exitcode}"}
                break
    proc.join()
    return record


def _run_isolated(case: Case, device: str, quick: bool = False) -> dict[str, Any]:
    if case.kind == "result":  # the job is its own process already
        try:
            record = time_to_result(JOBS[case.name], quick=quick)
        except RuntimeError as e:
            return {"name": case.name, "kind": case.kind, "error": str(e)}
        return {"name": case.name, "kind": case.kind, "device": device, "torch": torch.__version__, **record}
    return _isolated(run_case, (case, device), {"name": case.name, "kind": case.kind})


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("bench/results.json"))
    parser.add_argument("--plot", type=Path, default=None, help="scaling plot (default: next to --out)")
    parser.add_argument("--only", nargs="*", help="run only the cases whose name contains one of these; the "
                        "time-to-result cases (result/demo, result/synth_cpu_table: whole jobs, minutes) run only "
                        "when named here")
    parser.add_argument("--memory-limit-gb", type=float, default=16.0,
                        help="memory/dnri/largest_N/*: the budget a training step's peak must fit")
    parser.add_argument("--quick", action="store_true",
                        help="result/* cases at toy sizes: a check that the measurement runs, not a measurement")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--reference", type=Path, default=None,
                        help="a checkout of cgraber/cvpr_dNRI: also time its training step against ours (the "
                        "comparisons are named reference/<case>, so --only reference runs them alone)")
    parser.add_argument("--reference-size", choices=sorted(REFERENCE_SIZES), default="full",
                        help="full: the benchmark's sizes; tiny: toy sizes, a quick check that the comparison runs")
    parser.add_argument("--reference-rounds", type=int, default=4, help="alternating rounds of the comparison")
    parser.add_argument("--reference-iters", type=int, default=2, help="timed steps of each per round")
    parser.add_argument("--reference-threads", type=int, default=None,
                        help="torch threads of the comparison (default: torch's, as the other cases)")
    parser.add_argument("--allocator", choices=ALLOCATORS, default=None,
                        help="glibc's allocator settings in every case's process (default: $DIDER_ALLOCATOR, else "
                        "heap, as training runs; dider.perf.tune_allocator)")
    parser.add_argument("--bf16", choices=("auto", "yes", "no"), default="auto",
                        help="the bf16 cases: auto runs them where the device has native bf16 (a CPU without "
                        "AVX-512 emulates it, about 20x slower than fp32)")
    parser.add_argument("--profile", metavar="CASE", default=None,
                        help="instead of timing: profile one step of the training case CASE (e.g. "
                        "train/dnri/recurrent) with torch.profiler, print its op table and write it next to --out")
    parser.add_argument("--profile-rows", type=int, default=25, help="--profile: ops in the table")
    args = parser.parse_args(argv)
    if args.allocator:  # the spawned case processes read it at start (_worker)
        os.environ["DIDER_ALLOCATOR"] = args.allocator
    if args.profile is not None:
        trainable = {c.name: c for c in cases() if c.kind == "train"}
        if args.profile not in trainable:
            parser.error(f"--profile {args.profile!r}: not a training case; one of {', '.join(trainable)}")
        tune_allocator()  # in this process, as every case's worker does
        table = profile_case(trainable[args.profile], args.device, args.profile_rows)
        path = args.out.with_name(f"profile_{args.profile.replace('/', '_')}.txt")
        atomic_write_text(path, table)
        print(table)
        print(f"wrote {path}")
        return []
    native = native_bf16(args.device)
    bf16 = {"yes": True, "no": False, "auto": native}[args.bf16]
    meta = {"machine": platform.processor() or platform.machine(), "python": platform.python_version(),
            "cpus": os.cpu_count(), "gpu": torch.cuda.get_device_name() if args.device == "cuda" else None,
            "bf16": bf16, "native_bf16": native, "allocator": allocator_mode()}
    if not bf16:
        print(f"bf16 cases left out (--bf16 {args.bf16}; native bf16 on {args.device}: {native})", flush=True)

    def selected(name: str) -> bool:
        return (not args.only or any(s in name for s in args.only)) and (bf16 or "bf16" not in name)

    reference: dict[str, Any] | None = None
    names = tuple(n for n in REFERENCE_CASES if selected(f"reference/{n}"))
    if args.reference is not None and names:
        reference = _isolated(compare_with_reference, (args.reference, names, args.reference_size,
                                                       args.reference_rounds, args.reference_iters, 1, args.device,
                                                       args.reference_threads, bf16),
                              {"checkout": str(args.reference)})
        if "error" in reference:
            print(f"{'reference':<32} FAILED: {reference['error']}", flush=True)
        for name, r in reference.get("cases", {}).items():
            ours = ", ".join(f"{r['step_s'][k] * 1000:.1f} ({k}, speed-up {r['speedup'][k]:.2f}, matmul-only "
                             f"ceiling {r['ceiling']['speedup'][k]:.2f})" for k in r["speedup"])
            print(f"{'reference/' + name:<32} reference {r['step_s']['reference'] * 1000:9.1f} ms/step, ours {ours}",
                  flush=True)

    def write(records: list[dict[str, Any]]) -> None:
        document = {"meta": meta, "summary": summary(records, reference), "records": records}
        if reference is not None:
            document["reference"] = reference
        atomic_write_text(args.out, json.dumps(document, indent=2))

    records: list[dict[str, Any]] = []
    if reference is not None:
        write(records)
    for case in cases():
        if not selected(case.name) or (case.kind == "result" and not args.only):
            continue
        if case.kind == "largest":
            print(f"{case.name:<32} searching (budget {args.memory_limit_gb:g} GB)", flush=True)
            record = largest_case(case, records, args.device, args.memory_limit_gb)
        else:
            record = _run_isolated(case, args.device, args.quick)
        records.append(record)
        if "error" in record:
            print(f"{record['name']:<32} FAILED: {record['error']}", flush=True)
        elif case.kind == "largest":
            print(f"{record['name']:<32} largest N {record['largest_agents']} (next N: {record['bound']})", flush=True)
        elif case.kind == "result":
            print(f"{record['name']:<32} {record['wall_s']:9.1f} s for {record['runs']} run(s)", flush=True)
            for model, values in record["models"].items():
                print(f"    {model:<28} " + "  ".join(f"{k.removeprefix('test/')} {v:.3g}" for k, v in values.items()
                                                   if k != "runs"), flush=True)
        else:
            print(f"{record['name']:<32} {record['samples_per_s']:11.1f} samples/s  "
                  f"{record['step_s'] * 1000:9.1f} ms/step  peak {record['peak_memory_mb']:.0f} MiB", flush=True)
        write(records)  # after every case: an interrupted benchmark keeps what it measured
    derived = summary(records, reference)
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
