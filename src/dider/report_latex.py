"""The sweep report's table for a paper (``report.tex``): booktabs, one row per group, each cell the mean and
sample standard deviation over the seeds in three significant digits, the best mean of each column in bold
(lowest for errors and ratios, highest for recalls)."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from dider.report import Summary

# The columns a paper's table shows, in this order, where the sweep has them.
COLUMNS = (r"test/ade_vs_cv/h\d+", r"test/ade/h\d+", r"test/mse/h\d+", r"test/edge_acc/posterior/(none|interaction)")


def _tex(text: str) -> str:
    return re.sub(r"([_%&#$])", r"\\\1", str(text))


def _cell(mean: float, std: float, bold: bool) -> str:
    if not math.isfinite(mean):
        return "--"
    value = f"{mean:.3g}" if not bold else rf"\textbf{{{mean:.3g}}}"
    return value + ("" if not math.isfinite(std) else rf" $\pm$ {std:.2g}")


def columns(metrics: Sequence[str]) -> list[str]:
    return [m for pattern in COLUMNS for m in metrics if re.fullmatch(pattern, m)]


def latex_table(s: Summary, caption: str = "") -> str:
    """The table, as a LaTeX ``table`` environment (needs ``\\usepackage{booktabs}``)."""
    cols = columns(s.metrics)
    keys = list(dict.fromkeys(k for g in s.groups for k in g.key))
    stats = [[g.stats(m) for m in cols] for g in s.groups]
    best = []
    for j, m in enumerate(cols):
        means = [row[j][0] for row in stats]
        finite = [v for v in means if math.isfinite(v)]
        best.append((max if "edge_acc" in m else min)(finite) if finite else math.nan)
    head = [*(_tex(k) for k in keys), "$n$", *(_tex(m.removeprefix("test/")) for m in cols)]
    lines = [r"\begin{table}[t]", r"\centering", r"\begin{tabular}{" + "l" * (len(keys) + 1) + "r" * len(cols) + "}",
             r"\toprule", " & ".join(head) + r" \\", r"\midrule"]
    for g, row in zip(s.groups, stats, strict=True):
        cells = [_cell(mean, std, mean == best[j]) for j, (mean, std, _) in enumerate(row)]
        lines.append(" & ".join([*(_tex(g.key.get(k, "")) for k in keys), str(len(g.jobs)), *cells]) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}",
              r"\caption{" + _tex(caption or "Mean $\\pm$ sample standard deviation over seeds; best mean in bold. "
                                  "ade_vs_cv: position ADE over constant velocity's (below 1 beats it).") + "}",
              r"\end{table}"]
    return "\n".join(lines) + "\n"
