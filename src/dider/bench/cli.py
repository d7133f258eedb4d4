"""Running the cases, each in a fresh process, and the command line."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import multiprocessing as mp
import os
import platform
import re
import resource
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from queue import Empty
from typing import Any

import torch

from dider.bench.cases import CHECKPOINTING, Case, cases, memory_case
from dider.bench.data import data_case
from dider.bench.loop import loop_case
from dider.bench.memory import largest_agents
from dider.bench.reference import REFERENCE_CASES, REFERENCE_SIZES, compare_with_reference
from dider.bench.result import JOBS, time_to_result
from dider.bench.steps import gemm_case, model_case, profile_case
from dider.bench.summary import plot, summary
from dider.io import atomic_write_text
from dider.outputs.run_record import command_line, git_commit
from dider.perf import ALLOCATORS, allocator_mode, native_bf16, tune_allocator

log = logging.getLogger(__name__)


def _machine_memory_mb(device: str) -> float:
    if device == "cuda":
        return torch.cuda.get_device_properties(0).total_memory / 2**20
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**20


def largest_case(case: Case, records: list[dict[str, Any]], device: str,
                 limit_gb: float) -> dict[str, Any]:
    """The largest N whose training step peaks within ``limit_gb``
    (:func:`dider.bench.memory.largest_agents`), starting from this run's fixed-N memory records of
    the same setting."""
    checkpoint = bool(case.settings["checkpoint"])
    saver = "on" if checkpoint else "off"
    start = {r["settings"]["agents"]: r["peak_memory_mb"] for r in records
             if r["name"].startswith("memory/dnri/N") and r["name"].endswith(saver)
             and "error" not in r}

    def probe(n: int) -> float:
        record = _run_isolated(memory_case(n, checkpoint), device)
        print(f"    N = {n}: " + (f"peak {record['peak_memory_mb']:.0f} MiB"
                                  if "error" not in record
                                  else f"FAILED: {record['error']}"), flush=True)
        # killed: did not fit
        return float("inf") if "error" in record else record["peak_memory_mb"]

    t0 = time.perf_counter()
    found = largest_agents(probe, limit_gb * 1024, 0.85 * _machine_memory_mb(device), start)
    return {"name": case.name, "kind": case.kind, "device": device, "torch": torch.__version__,
            "limit_gb": limit_gb, "search_s": time.perf_counter() - t0, **found,
            "settings": {"batch": case.batch, "steps": case.steps, "overrides": ["model=dnri"]
                         + (CHECKPOINTING if checkpoint else []), "checkpoint": checkpoint}}


def run_case(case: Case, device: str, tmpdir: str | None = None) -> dict[str, Any]:
    if case.kind in ("train", "rollout"):
        step_s, extra = model_case(case, device)
    elif case.kind == "job":
        step_s, extra = loop_case(case, device)
    elif case.kind == "gemm":
        step_s, extra = gemm_case(case, device)
    else:
        step_s, extra = data_case(case, device, tmpdir)
    peak = (torch.cuda.max_memory_allocated()
            if device == "cuda" and case.kind in ("train", "rollout")
            else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
    rate = {"gflops": extra["gflop_per_step"] / step_s} if "gflop_per_step" in extra else {}
    return {
        "name": case.name, "kind": case.kind, "samples_per_s": case.batch / step_s,
        "step_s": step_s, **rate,
        "peak_memory_mb": peak / 2**20, "device": device, "threads": torch.get_num_threads(),
        "torch": torch.__version__, "allocator": allocator_mode(),
        "settings": {"batch": case.batch, "agents": case.agents, "steps": case.steps,
                     "iters": case.iters, "overrides": case.overrides, **case.settings, **extra},
    }  # fmt: skip


def _worker(fn: Callable[..., dict[str, Any]], args: tuple[Any, ...], failed: dict[str, Any],
            queue: mp.Queue) -> None:
    tune_allocator()
    try:
        queue.put(fn(*args))
    # a failed case is reported as such and the others still run
    except Exception as e:  # noqa: BLE001
        queue.put({**failed, "error": f"{type(e).__name__}: {e}"})


def _isolated(fn: Callable[..., dict[str, Any]], args: tuple[Any, ...],
              failed: dict[str, Any]) -> dict[str, Any]:
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
        return {"name": case.name, "kind": case.kind, "device": device, "torch": torch.__version__,
                **record}
    return _isolated(run_case, (case, device), {"name": case.name, "kind": case.kind})


def _pattern(text: str) -> re.Pattern[str]:
    try:
        return re.compile(text)
    except re.error as err:
        raise argparse.ArgumentTypeError(
            f"--only {text!r}: not a regular expression ({err})") from err


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m dider.bench", description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("bench/results.json"))
    parser.add_argument("--plot", type=Path, default=None,
                        help="scaling plot (default: next to --out)")
    parser.add_argument("--only", nargs="*", type=_pattern,
                        help="run only the cases whose name matches one of these regular "
                        "expressions (searched anywhere in the name: a plain name selects the "
                        "cases that contain it, 'train/dnri/synth$' that case alone); the "
                        "time-to-result cases (result/demo, result/synth_cpu_table: whole jobs, "
                        "minutes) run only when named here")
    parser.add_argument("--memory-limit-gb", type=float, default=16.0,
                        help="memory/dnri/largest_N/*: the budget a training step's peak must fit")
    parser.add_argument("--quick", action="store_true",
                        help="result/* cases at toy sizes: a check that the measurement runs, not "
                        "a measurement")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--reference", type=Path, default=None,
                        help="a checkout of cgraber/cvpr_dNRI: also time its training step against "
                        "ours (the comparisons are named reference/<case>, so --only reference "
                        "runs them alone)")
    parser.add_argument("--reference-size", choices=sorted(REFERENCE_SIZES), default="full",
                        help="full: the benchmark's sizes; tiny: toy sizes, a quick check that the "
                        "comparison runs")
    parser.add_argument("--reference-rounds", type=int, default=4,
                        help="alternating rounds of the comparison")
    parser.add_argument("--reference-iters", type=int, default=2,
                        help="timed steps of each per round")
    parser.add_argument("--reference-threads", type=int, default=None,
                        help="torch threads of the comparison (default: torch's, as the other "
                        "cases)")
    parser.add_argument("--allocator", choices=ALLOCATORS, nargs="+", default=None,
                        help="glibc's allocator settings in every case's process (default: "
                        "$DIDER_ALLOCATOR, else heap, as training runs; "
                        "dider.perf.tune_allocator); two or more: every case runs under each in "
                        "turn, --allocator-rounds times, and the summary pairs them by round")
    parser.add_argument("--allocator-rounds", type=int, default=3,
                        help="rounds of an --allocator comparison (the order alternates: A B, B A, "
                        "A B, ...)")
    parser.add_argument("--bf16", choices=("auto", "yes", "no"), default="auto",
                        help="the bf16 cases: auto runs them where the device has native bf16 (a "
                        "CPU without AVX-512 emulates it, far slower than fp32)")
    parser.add_argument("--profile", metavar="CASE", default=None,
                        help="instead of timing: profile one step of the training case CASE (e.g. "
                        "train/dnri/recurrent) with torch.profiler, print its op table and write "
                        "it next to --out")
    parser.add_argument("--profile-rows", type=int, default=25, help="--profile: ops in the table")
    return parser


def _profile(args: argparse.Namespace, parser: argparse.ArgumentParser) -> None:
    """--profile: one step of a training case under torch.profiler, its op table printed and
    written."""
    trainable = {c.name: c for c in cases() if c.kind == "train"}
    if args.profile not in trainable:
        parser.error(f"--profile {args.profile!r}: not a training case; one of "
                     f"{', '.join(trainable)}")
    tune_allocator()  # in this process, as every case's worker does
    table = profile_case(trainable[args.profile], args.device, args.profile_rows)
    path = args.out.with_name(f"profile_{args.profile.replace('/', '_')}.txt")
    atomic_write_text(path, table)
    print(table)
    print(f"wrote {path}")


def _reference(args: argparse.Namespace, names: tuple[str, ...], bf16: bool) -> dict[str, Any]:
    """The public DNRI code's training step against ours on the cases ``names``, in a process of its
    own."""
    reference = _isolated(compare_with_reference, (args.reference, names, args.reference_size,
                                                   args.reference_rounds, args.reference_iters, 1,
                                                   args.device, args.reference_threads, bf16),
                          {"checkout": str(args.reference)})
    if "error" in reference:
        print(f"{'reference':<32} FAILED: {reference['error']}", flush=True)
    for name, r in reference.get("cases", {}).items():
        ours = ", ".join(f"{r['step_s'][k] * 1000:.1f} ({k}, speed-up {r['speedup'][k]:.2f}, "
                         f"matmul-only ceiling {r['ceiling']['speedup'][k]:.2f})"
                         for k in r["speedup"])
        print(f"{'reference/' + name:<32} reference {r['step_s']['reference'] * 1000:9.1f} "
              f"ms/step, ours {ours}",
              flush=True)
    return reference


def _alternating(modes: list[str], rounds: int) -> list[tuple[int, str]]:
    """(round, allocator) in the order they run: every round each setting once, the order reversed
    every other round, so a drift of the machine's speed within the rounds falls on both alike."""
    return [(r, m) for r in range(rounds) for m in (modes if r % 2 == 0 else modes[::-1])]


def _print_record(case: Case, record: dict[str, Any]) -> None:
    if "error" in record:
        print(f"{record['name']:<32} FAILED: {record['error']}", flush=True)
    elif case.kind == "largest":
        print(f"{record['name']:<32} largest N {record['largest_agents']} (next N: "
              f"{record['bound']})", flush=True)
    elif case.kind == "result":
        print(f"{record['name']:<32} {record['wall_s']:9.1f} s for {record['runs']} run(s)",
              flush=True)
        for model, values in record["models"].items():
            print(f"    {model:<28} " + "  ".join(f"{k.removeprefix('test/')} {v:.3g}"
                                                  for k, v in values.items()
                                               if k != "runs"), flush=True)
    else:
        where = f"  ({record['allocator']}, round {record['round']})" if "round" in record else ""
        print(f"{record['name']:<32} {record['samples_per_s']:11.1f} samples/s  "
              f"{record['step_s'] * 1000:9.1f} ms/step  peak {record['peak_memory_mb']:.0f} "
              f"MiB{where}", flush=True)


@contextlib.contextmanager
def _allocator_env(mode: str | None) -> Iterator[None]:
    """The case processes spawned inside take ``mode`` (they read ``$DIDER_ALLOCATOR`` at start,
    ``_worker``); the variable is restored on leaving. None: leave it as it is."""
    old = os.environ.get("DIDER_ALLOCATOR")
    if mode is not None:
        os.environ["DIDER_ALLOCATOR"] = mode
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("DIDER_ALLOCATOR", None)
        else:
            os.environ["DIDER_ALLOCATOR"] = old


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = _parser()
    args = parser.parse_args(argv)
    if (args.allocator and len(set(args.allocator)) != len(args.allocator)
        or args.allocator_rounds < 1):
        parser.error("--allocator: distinct settings and --allocator-rounds >= 1, got "
                     f"{args.allocator} and {args.allocator_rounds}")
    with _allocator_env(args.allocator[0] if args.allocator else None):
        if args.profile is not None:
            _profile(args, parser)
            return []
        return _bench(args, command_line(parser.prog, argv))


def _bench(args: argparse.Namespace, command: str) -> list[dict[str, Any]]:
    """Every selected case (each in a fresh process), the JSON rewritten after each measurement."""
    modes = args.allocator or [allocator_mode()]
    native = native_bf16(args.device)
    bf16 = {"yes": True, "no": False, "auto": native}[args.bf16]
    meta = {"command": command, "git_commit": git_commit(),
            "machine": platform.processor() or platform.machine(),
            "python": platform.python_version(), "cpus": os.cpu_count(),
            "gpu": torch.cuda.get_device_name() if args.device == "cuda" else None, "bf16": bf16,
            "native_bf16": native, "allocator": modes[0] if len(modes) == 1 else modes}
    if not bf16:
        print(f"bf16 cases left out (--bf16 {args.bf16}; native bf16 on {args.device}: {native})",
              flush=True)

    def selected(name: str) -> bool:
        # the job cases' eager twins only where the default graphs the step (a CUDA device)
        graphs = args.device == "cuda" or not name.endswith("/eager")
        return ((not args.only or any(p.search(name) for p in args.only))
                and (bf16 or "bf16" not in name) and graphs)

    names = tuple(n for n in REFERENCE_CASES if selected(f"reference/{n}"))
    reference = _reference(args, names, bf16) if args.reference is not None and names else None
    records: list[dict[str, Any]] = []

    def write() -> None:
        document = {"meta": meta, "summary": summary(records, reference), "records": records}
        if reference is not None:
            document["reference"] = reference
        atomic_write_text(args.out, json.dumps(document, indent=2))

    def measure(case: Case) -> Iterator[dict[str, Any]]:
        if case.kind == "largest":
            print(f"{case.name:<32} searching (budget {args.memory_limit_gb:g} GB)", flush=True)
            yield largest_case(case, records, args.device, args.memory_limit_gb)
        # a result case is a training job: its config's allocator
        elif len(modes) == 1 or case.kind == "result":
            yield _run_isolated(case, args.device, args.quick)
        else:
            for round_, mode in _alternating(modes, args.allocator_rounds):
                with _allocator_env(mode):
                    record = _run_isolated(case, args.device)
                yield {**record, "round": round_}

    if reference is not None:
        write()
    for case in cases():
        if not selected(case.name) or (case.kind == "result" and not args.only):
            continue
        for record in measure(case):
            records.append(record)
            _print_record(case, record)
            write()  # after every measurement: an interrupted benchmark keeps what it measured
    for key, value in summary(records, reference).items():
        print(f"{key:<44} {value:.2f}")
    if any(r["name"].startswith("scale/") for r in records):
        plot(records, args.plot or args.out.with_suffix(".png"))
    print(f"wrote {args.out}")
    return records


def cli() -> None:
    """The console script (``dider-bench``): ``main`` without its return value (an exit status of
    0)."""
    main()


if __name__ == "__main__":
    main()
