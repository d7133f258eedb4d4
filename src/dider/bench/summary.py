"""What a benchmark run adds up to: derived figures (speed-ups, the roofline, growth exponents) and
the scaling plot, from the per-case records that :mod:`dider.bench` writes."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from dider.bench.reference import REFERENCE_CASES


def summary(records: list[dict[str, Any]],
            reference: dict[str, Any] | None = None) -> dict[str, Any]:
    """Derived figures: DIDER's step time over DNRI's (same run); the growth exponents of the step
    time in N, in the edge count N(N-1) and in T (least-squares slopes on log-log axes; the budgets:
    N^2, i.e. 1 in edges, and 1 in T); speed-ups over the reference implementation; and the
    roofline, the samples/s a step would reach doing only its matmuls at the measured ``gemm/*``
    rate.

    ``reference``: the results JSON's ``reference`` section
    (:func:`dider.bench.compare_with_reference`). The speed-ups come only from there (reference and
    ours timed in the same process, alternating), with the matmul-only ceiling of the same run
    beside them: a throughput measured on another machine or at another time is no denominator for
    this run's."""
    by = {r["name"]: r for r in records if "error" not in r}
    measured = (reference or {}).get("cases", {})
    out: dict[str, Any] = {}
    for name, case in measured.items():
        for dtype, variant in (("fp32", ""), ("bf16", "/bf16")):
            # ours in bf16 against the reference in fp32; bf16 may be left out
            if dtype in case["speedup"]:
                out[f"speedup_over_reference/{name}{variant}"] = case["speedup"][dtype]
                ceiling = case.get("ceiling", {}).get("speedup", {})  # absent in older JSON
                if dtype in ceiling:  # the most any implementation of our arithmetic reaches here
                    out[f"ceiling_over_reference/{name}{variant}"] = ceiling[dtype]
    for dtype in ("fp32", "bf16"):
        if f"gemm/{dtype}" not in by:
            continue
        peak = by[f"gemm/{dtype}"]["gflops"]
        for name in REFERENCE_CASES:
            settings = by[name]["settings"] if name in by else {}
            if "gflop_per_step" in settings:
                ceiling = settings["batch"] * peak / settings["gflop_per_step"]
                out[f"roofline/{dtype}/{name}/max_samples_per_s"] = ceiling
    for setting in ("synth", "recurrent"):
        for model in ("dider", "dider_skid"):
            a, b = by.get(f"train/{model}/{setting}"), by.get(f"train/dnri/{setting}")
            if a and b:
                out[f"step_ratio/{model}_over_dnri/{setting}"] = a["step_s"] / b["step_s"]
    for axis, key in (("agents", "agents"), ("steps", "steps")):
        pts = [(r["settings"][key], r["step_s"]) for r in by.values()
               if r["name"].startswith(f"scale/{axis}/")]
        if len(pts) >= 2:
            x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
            out[f"growth_exponent/{axis}"] = float(np.polyfit(x, y, 1)[0])
            if axis == "agents":  # against the edge count N(N-1): 1 means "as N^2 for large N"
                edges = np.log([p[0] * (p[0] - 1) for p in pts])
                out["growth_exponent/edges"] = float(np.polyfit(edges, y, 1)[0])
    return out | allocator_ratios(records)


def allocator_ratios(records: list[dict[str, Any]]) -> dict[str, float]:
    """An ``--allocator A B ...`` comparison: for each case, the median over the rounds of each
    setting's step time and peak memory over the first setting's in the same round
    (``allocator/B_over_A/<case>/step`` and ``/peak``); records without a ``round`` (a plain run)
    give nothing."""
    rounds: dict[str, dict[int, dict[str, dict[str, Any]]]] = {}
    for r in records:
        if "round" in r and "error" not in r:
            rounds.setdefault(r["name"], {}).setdefault(r["round"], {})[r["allocator"]] = r
    out: dict[str, float] = {}
    for name, by_round in rounds.items():
        # round 0 runs the settings in the order they were given
        base, *others = by_round[min(by_round)]
        for mode in others:
            pairs = [(rd[mode], rd[base]) for rd in by_round.values() if mode in rd and base in rd]
            if pairs:
                for key, field in (("step", "step_s"), ("peak", "peak_memory_mb")):
                    out[f"allocator/{mode}_over_{base}/{name}/{key}"] = float(
                        np.median([a[field] / b[field]
                                 for a, b in pairs]))
    return out


def plot(records: list[dict[str, Any]], path: Path) -> None:
    """Step time against N and T on log-log axes, with N^2 and T^1 guides through the first
    point."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.8))
    guides = {"agents": ("∝ N(N-1) edges", lambda n: n * (n - 1)), "steps": ("∝ T", lambda t: t)}
    for ax, axis, key in ((axes[0], "agents", "agents"), (axes[1], "steps", "steps")):
        pts = sorted((r["settings"][key], r["step_s"]) for r in records
                     if "error" not in r and r["name"].startswith(f"scale/{axis}/"))
        if not pts:
            continue
        x, y = np.array(pts).T
        label, grow = guides[axis]
        ax.loglog(x, y, "o-", label="measured")
        ax.loglog(x, y[0] * grow(x) / grow(x[0]), "--", color="grey", label=label)
        ax.set_xticks(x, [str(int(v)) for v in x])
        ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        ax.set_xlabel("agents N (T = 50)" if axis == "agents" else "steps T (N = 5)")
        ax.set_ylabel("training step (s)")
        ax.legend(fontsize=8)
    fig.suptitle("DNRI training step, batch 8 (narrow networks)", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=path.parent, suffix=path.suffix, delete=False) as tmp:
        fig.savefig(tmp.name, dpi=100)
    Path(tmp.name).replace(path)
    plt.close(fig)
