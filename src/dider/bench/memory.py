"""The largest scene that trains within a memory budget: a search over the number of agents N.

A training step's peak grows with the edges, a + b * N (N - 1). The search measures a few N (each a
fresh process, so each peak is its own), fits that line through the two largest measured so far to
aim at the budget, then bisects between the largest N that fitted and the smallest that did not. It
never starts a probe whose predicted peak exceeds ``ceiling_mb`` (the machine's memory, with a
margin): such an N counts as not fitting, and the record says the bound was predicted, not measured.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any


def _edges(n: int) -> int:
    return n * (n - 1)


def _line(probes: dict[int, float]) -> tuple[int, float, float]:
    """The line through the two largest measured N, in edges: (N, its peak, MB per edge)."""
    (n1, p1), (n0, p0) = sorted(probes.items(), reverse=True)[:2]
    return n1, p1, (p1 - p0) / max(_edges(n1) - _edges(n0), 1)


def _predict(probes: dict[int, float], n: int) -> float:
    """Peak at N = n from :func:`_line`."""
    n1, p1, slope = _line(probes)
    return p1 + slope * (_edges(n) - _edges(n1))


def _aim(probes: dict[int, float], limit_mb: float, lo: int) -> int:
    """The N the fitted line puts at the budget (at least lo + 1)."""
    n1, p1, slope = _line(probes)
    edges = _edges(n1) + (limit_mb - p1) / max(slope, 1e-9)
    return max(lo + 1, int((1 + math.sqrt(1 + 4 * max(edges, 0.0))) / 2))


def largest_agents(probe: Callable[[int], float], limit_mb: float, ceiling_mb: float,
                   start: dict[int, float] | None = None, max_probes: int = 8) -> dict[str, Any]:
    """The largest N with ``probe(N) <= limit_mb`` (``probe``: N -> measured peak in MB).

    ``start``: peaks already measured (e.g. the fixed memory cases). Returns ``largest_agents``
    (None when even the smallest measured N does not fit), ``bound`` (``measured`` when N + 1 was
    run and did not fit, ``predicted`` when its predicted peak was over ``ceiling_mb`` so it was not
    run, ``probes`` when the probe budget ran out) and the ``probes`` {N: peak MB}."""
    probes: dict[int, float] = dict(start or {})
    predicted: dict[int, float] = {}
    if not probes:
        probes[2] = probe(2)
    if len(probes) == 1:  # a line needs two points: a smaller scene
        (n0,) = probes
        n1 = max(2, n0 // 2) if n0 > 2 else 3
        probes[n1] = probe(n1)
    fits = [n for n, p in probes.items() if p <= limit_mb]
    over = [n for n, p in probes.items() if p > limit_mb]
    lo, hi = max(fits, default=None), min(over, default=None)
    if lo is None:
        return {"largest_agents": None, "bound": "measured", "probes": probes,
                "predicted": predicted}
    runs = 0
    while (hi is None or hi - lo > 1) and runs < max_probes:
        n = _aim(probes, limit_mb, lo) if hi is None else (lo + hi) // 2
        if hi is not None:
            n = min(max(n, lo + 1), hi - 1)
        guess = _predict(probes, n)
        if guess > ceiling_mb:  # would not fit the machine itself: do not run it
            predicted[n] = guess
            hi = n if hi is None else min(hi, n)
            continue
        probes[n] = probe(n)
        runs += 1
        if probes[n] <= limit_mb:
            lo = n
        else:
            hi = n
    bound = ("probes" if hi is None or hi - lo > 1
             else ("predicted" if hi in predicted else "measured"))
    return {"largest_agents": lo, "bound": bound, "probes": dict(sorted(probes.items())),
            "predicted": dict(sorted(predicted.items()))}
