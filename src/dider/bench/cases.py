"""The benchmark's cases: what each times, at which sizes (``python -m dider.bench``)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

from dider.bench.result import JOBS

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
    # train | job | rollout | generate | preprocess | load | outputs | gemm | largest | result
    kind: str = "train"


# The encoder's edge-MLP matmul at batch 128, N = 3, T = 50: [B*T*E, 256] x [256, 256].
GEMM_SHAPE = (128 * 50 * 6, 256, 256)

SCALE_AGENTS = (3, 5, 10, 20, 50)
OUTPUT_AGENTS = (40, 100)
SCALE_STEPS = (50, 100, 200)
# The scaling series: DNRI's step with narrower networks (N = 50 has 2450 edges; full width would
# need tens of GB), so the growth in N and T shows, not the constant. The overrides that leave the
# sparsity term out, the edge KL at full weight (also the tests').
NO_SPARSITY = ["model.net.objective.sparsity=null", "model.net.objective.kl_edge.weight=1"]
SCALE_MODEL = ["model=dnri", "model.net.encoder.hidden=64", "model.net.decoder.hidden=64",
               *NO_SPARSITY]


# Peak memory of one DNRI step at the paper's widths (batch 8), activation checkpointing off and on.
MEMORY_AGENTS = (10, 20, 30)
CHECKPOINTING = ["model.net.encoder.checkpoint=true", "model.net.decoder.checkpoint=true"]


def memory_case(agents: int, checkpoint: bool) -> Case:
    """One DNRI training step at the paper's widths, batch 8, T 50: its peak is the figure."""
    return Case(f"memory/dnri/N{agents:02d}/checkpoint_{'on' if checkpoint else 'off'}",
                ["model=dnri", *(CHECKPOINTING if checkpoint else [])], 8, agents, 50, iters=1,
                warmup=0, settings={"count_flops": False, "checkpoint": checkpoint})


def cases() -> list[Case]:
    recurrent = ["model/net/decoder=recurrent", *NO_SPARSITY]
    out = [Case(f"gemm/{dtype}", [], 1, 0, 0, iters=20, warmup=3, kind="gemm",
                settings={"dtype": dtype})
           for dtype in ("fp32", "bf16")]
    for model in ("dnri", "dider", "dider_skid"):
        out.append(Case(f"train/{model}/synth", [f"model={model}"], 128, 3, 50))
        out.append(Case(f"train/{model}/recurrent", [f"model={model}", *recurrent], 128, 5, 40,
                        iters=3))
    out.append(Case("train/dnri/recurrent/bf16", ["model=dnri", *recurrent], 128, 5, 40, iters=3,
                    settings={"autocast": "bf16"}))
    # a real job's step, the Lightning loop included: the paper's batch and 128; on a GPU as one
    # CUDA graph and eagerly
    for model in ("dnri", "dider", "dider_skid"):
        for batch in (16, 128):
            for graph, suffix in (("auto", ""), ("false", "/eager")):
                out.append(Case(f"job/{model}/synth/b{batch:03d}{suffix}",
                                [f"model={model}", f"cuda_graph={graph}"],
                                batch, 3, 50, iters=20, warmup=5, kind="job"))
    for model in ("dnri", "dider"):
        out.append(Case(f"train/{model}/synth/bf16", [f"model={model}"], 128, 3, 50,
                        settings={"autocast": "bf16"}))
        out.append(Case(f"train/{model}/synth/compile", [f"model={model}"], 128, 3, 50, warmup=3,
                        settings={"compile": True}))
        out.append(Case(f"rollout/{model}/synth", [f"model={model}"], 256, 3, 50, kind="rollout"))
    out.append(Case("generate/synth/40k", [], 40000, 3, 50, iters=1, warmup=0, kind="generate"))
    out.append(Case("preprocess/ind/20min_300tracks", [], 1, 300, 30000, iters=1, warmup=0,
                    kind="preprocess"))
    for workers in (0, 2):
        out.append(Case(f"load/synth/workers{workers}", [], 128, 3, 50, iters=1, warmup=0,
                        kind="load", settings={"num_workers": workers}))
    # the end-of-run outputs of a test set of 64 clips (step_s: all of them)
    for n in OUTPUT_AGENTS:
        out.append(Case(f"outputs/N{n:03d}", [], 64, n, 50, iters=1, warmup=0, kind="outputs"))
    for n in SCALE_AGENTS:
        out.append(Case(f"scale/agents/N{n:02d}", SCALE_MODEL, 8, n, 50, iters=3, warmup=1))
    for t in SCALE_STEPS:
        out.append(Case(f"scale/steps/T{t:03d}", SCALE_MODEL, 8, 5, t, iters=3, warmup=1))
    # one step each: the peak is the figure (N = 30: about 40 s on 2 cores, bench_memory.json)
    for n in MEMORY_AGENTS:
        for saver in ("off", "on"):
            out.append(memory_case(n, saver == "on"))
    for saver in ("off", "on"):  # after the fixed N above, whose peaks start the search
        out.append(Case(f"memory/dnri/largest_N/checkpoint_{saver}", [], 8, 0, 50, iters=1,
                        warmup=0, kind="largest", settings={"checkpoint": saver == "on"}))
    out += [Case(name, [], 0, 0, 0, iters=1, warmup=0, kind="result") for name in JOBS]
    return out


