"""The sweep report's statistics, through pandas: one row per job, grouped by the swept keys; the
mean, sample standard deviation, count and Student-t 95% half-width of each metric; ratios to a
baseline model paired by seed; cells printed with one number of decimals per column; the best mean
of a column marked, and whether a paired comparison over the seeds supports it."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

if TYPE_CHECKING:
    from dider.analysis.report import Group

# Student's t 97.5% quantiles for 1..30 degrees of freedom: a 95% band over a few seeds is much
# wider than the normal 1.96 (4 seeds: 3.18).
T975 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160,
        2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056,
        2.052, 2.048, 2.045, 2.042)
BASELINE = "dnri"  # the ratio columns' model, when the sweep has it
# the errors a ratio column divides (data units: a ratio is unit-free)
RATIO_OF = r"test/(ade|fde)/h\d+"
# not cv/
LOWER_IS_BETTER = (
    r"test/(ade|fde|ade_vs_cv|(ade|fde)_vs_\w+|mse\w*|(min_ade|min_fde|miss_rate)_\d+)/h\d+")
HIGHER_IS_BETTER = r"test/(edge_acc/.*|boundary_f1)"


def t975(df: int) -> float:
    """The 97.5% quantile of Student's t with ``df`` degrees of freedom (NaN for df < 1); beyond the
    table, the Cornish-Fisher expansion around 1.96 (error < 1e-3 for df > 30)."""
    if df < 1:
        return math.nan
    if df <= len(T975):
        return T975[df - 1]
    z = 1.959964
    return z + (z**3 + z) / (4 * df) + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * df**2)


def jobs_frame(groups: Sequence[Group], metrics: Sequence[str]) -> pd.DataFrame:
    """One row per job: ``group`` (its index in ``groups``), the group's key columns, ``seed`` and
    the metrics (NaN where a job did not log one)."""
    rows = [{"group": i, **g.key, "seed": j.get("seed"),
             **{m: j["metrics"].get(m, math.nan) for m in metrics}}
            for i, g in enumerate(groups) for j in g.jobs]
    columns = ["group", *dict.fromkeys(k for g in groups for k in g.key), "seed", *metrics]
    return pd.DataFrame(rows, columns=columns).astype({m: float for m in metrics})


def group_stats(frame: pd.DataFrame, metrics: Sequence[str]) -> pd.DataFrame:
    """Per group (the index) and metric: columns (metric, stat) with stat in mean, std (n-1), n,
    ci95 (the Student-t half-width of the mean's 95% interval; NaN for one job)."""
    by = frame.groupby("group", sort=True)[list(metrics)]
    n = by.count()
    std = by.std(ddof=1)
    t = pd.DataFrame(np.vectorize(lambda k: t975(int(k) - 1))(n.to_numpy()), index=n.index,
                     columns=n.columns)
    half = std * t / np.sqrt(n.clip(lower=1))
    stats = pd.concat({"mean": by.mean(), "std": std, "n": n, "ci95": half}, axis=1)
    return stats.swaplevel(axis=1)


def add_ratios(groups: Sequence[Group], baseline: str = BASELINE) -> list[str]:
    """Adds to every job's metrics ``test/ade_vs_<baseline>/hXX`` (and fde): its error over the
    baseline model's on the same seed and the same other swept settings; num_edges too when the
    baseline ran with several (the models of a table may differ in it otherwise). Returns the new
    metric names: none when the sweep has no baseline job or nothing but baseline jobs. Jobs without
    a seed, and seeds the baseline ran twice with the same settings, get no ratio (their pairing is
    ambiguous)."""
    baseline_groups = [g for g in groups if g.key.get("model") == baseline]
    if not baseline_groups or len(baseline_groups) == len(groups):
        return []
    several = len({g.key.get("num_edges") for g in baseline_groups}) > 1
    keys = [k for k in dict.fromkeys(k for g in groups for k in g.key)
            if k != "model" and (k != "num_edges" or several)]
    index: dict[tuple, dict[str, Any] | None] = {}
    for g in baseline_groups:
        for j in g.jobs:
            if j.get("seed") is not None:
                pair = (tuple(g.key.get(k) for k in keys), j["seed"])
                index[pair] = None if pair in index else j["metrics"]  # a second job: ambiguous
    added: set[str] = set()
    for g in groups:
        for j in g.jobs:
            base = index.get((tuple(g.key.get(k) for k in keys), j.get("seed")))
            if base is None:
                continue
            for m, v in list(j["metrics"].items()):
                if re.fullmatch(RATIO_OF, m) and base.get(m):
                    name = re.sub(r"^test/(\w+)/", rf"test/\1_vs_{baseline}/", m)
                    j["metrics"][name] = v / base[m]
                    added.add(name)
    return sorted(added)


def direction(metric: str) -> int:
    """-1: lower is better, +1: higher is better, 0: neither (a description, e.g. a type's mean
    distance)."""
    return (-1 if re.fullmatch(LOWER_IS_BETTER, metric) else 1
            if re.fullmatch(HIGHER_IS_BETTER, metric) else 0)


@dataclass(frozen=True)
class ColumnFormat:
    """One column's printing: values times 10**-exponent, ``decimals`` after the point for mean and
    std alike."""
    exponent: int
    decimals: int

    @classmethod
    def of(cls, means: Sequence[float], digits: int = 3) -> ColumnFormat:
        """``digits`` significant digits for the column's largest |mean|; a power of ten in the
        header when the values are below 0.01 or from 10^4."""
        finite = [abs(v) for v in means if math.isfinite(v) and v != 0]
        if not finite:
            return cls(0, digits - 1)
        top = math.floor(math.log10(max(finite)))
        exponent = top if top < -2 or top >= 4 else 0
        return cls(exponent, max(0, digits - 1 - (top - exponent)))

    def header(self, name: str) -> str:
        return name if self.exponent == 0 else f"{name} (×1e{self.exponent})"

    def cell(self, mean: float, std: float = math.nan) -> tuple[str, str]:
        """(mean, std) as printed; "" for a missing std, "–" for a missing mean."""
        if not math.isfinite(mean):
            return "–", ""
        scale = 10.0**-self.exponent
        return (f"{mean * scale:.{self.decimals}f}",
                f"{std * scale:.{self.decimals}f}" if math.isfinite(std) else "")


def best_row(stats: pd.DataFrame, metric: str) -> int | None:
    """The group with the best mean of ``metric`` (None: no direction, or fewer than two groups with
    a value)."""
    sign = direction(metric)
    means = stats[(metric, "mean")].dropna()
    # a ratio to a reference: the reference's own row (1, every seed) is no rival
    if re.search(r"_vs_\w+/", metric):
        means = means[~((means == 1) & (stats[(metric, "std")].fillna(0) == 0))]
    if sign == 0 or len(means) < 2:
        return None
    best = means.idxmax() if sign > 0 else means.idxmin()
    return None if int((means == means[best]).sum()) > 1 else int(best)  # a tie has no best row


def paired_support(frame: pd.DataFrame, best: int, metric: str) -> tuple[bool, int, Any]:
    """Whether group ``best`` beats every other group with a value of ``metric``, paired by seed:
    the 95% Student-t interval of the per-seed differences excludes 0 on the better side. Jobs
    without a seed are left out; a group that ran a seed twice, or shares fewer than two seeds with
    ``best``, is not beaten. -> (supported, the fewest seeds paired, the first group it is not
    established against, or None)."""
    sign = direction(metric) or -1
    rows = frame[frame["seed"].notna() & frame[metric].notna()]
    others = [g for g in dict.fromkeys(frame.loc[frame[metric].notna(), "group"]) if g != best]
    fewest = None
    for other in others:
        pair = rows[rows["group"].isin([best, other])]
        if pair.duplicated(["group", "seed"]).any():
            return False, 0, other
        table = pair.pivot(index="seed", columns="group", values=metric)
        if best in table and other in table:
            diff = (table[best] - table[other]).dropna().to_numpy() * sign  # > 0: best is better
        else:
            diff = np.array([])
        n = len(diff)
        fewest = n if fewest is None else min(fewest, n)
        if n < 2 or diff.mean() - t975(n - 1) * diff.std(ddof=1) / math.sqrt(n) <= 0:
            return False, n, other
    return bool(others), fewest or 0, None


BEST_NOTE = ("the best mean of a column in bold, with † where it beats every other row paired by "
             "seed (the 95% Student-t interval of the per-seed differences excludes 0); bold "
             "without † is not established at this n")


def marked_cells(stats: pd.DataFrame, frame: pd.DataFrame, metric: str, bold: tuple[str, str],
                 dagger: str) -> tuple[ColumnFormat, list[tuple[str, str]]]:
    """One column: its format and its cells by group, (mean, std) as printed with the column's
    decimals; the best mean wrapped in ``bold`` and followed by ``dagger`` when a comparison paired
    by seed supports it against every other row."""
    means, stds = stats[(metric, "mean")], stats[(metric, "std")]
    fmt = ColumnFormat.of(list(means))
    cells = [fmt.cell(mean, std) for mean, std in zip(means, stds, strict=True)]
    best = best_row(stats, metric)
    if best is not None:
        dag = dagger if paired_support(frame, best, metric)[0] else ""
        cells[best] = (bold[0] + cells[best][0] + bold[1] + dag, cells[best][1])
    return fmt, cells
