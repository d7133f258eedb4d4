"""The sweep report's table for a paper (``report.tex``): booktabs, one row per group, each cell the
mean and sample standard deviation over the seeds with one number of decimals per column, the best
mean of each column in bold (lowest for errors and ratios, highest for recalls), with a dagger where
a comparison paired by seed supports it."""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import TYPE_CHECKING

from dider.analysis.report_table import ColumnFormat, marked_cells

if TYPE_CHECKING:
    from dider.analysis.report import Summary

# The columns a paper's table shows, in this order, where the sweep has them.
COLUMNS = (r"test/ade_vs_cv/h\d+", r"test/ade_vs_dnri/h\d+", r"test/ade/h\d+", r"test/mse/h\d+",
           r"test/edge_acc/posterior/(none|interaction)")


def _tex(text: str) -> str:
    return re.sub(r"([_%&#$])", r"\\\1", str(text))


def columns(metrics: Sequence[str]) -> list[str]:
    return [m for pattern in COLUMNS for m in metrics if re.fullmatch(pattern, m)]


def _header(metric: str, fmt: ColumnFormat) -> str:
    name = _tex(metric.removeprefix("test/"))
    return name if fmt.exponent == 0 else rf"{name} ($\times 10^{{{fmt.exponent}}}$)"


# The most value columns one tabular holds beside the keys: wider tables are split into stacked
# tabulars (each with the keys again), so a table of a dozen metrics still fits a page's width.
MAX_COLUMNS = 5


def latex_table(s: Summary, caption: str = "") -> str:
    """The table, as a LaTeX ``table`` environment (needs ``\\usepackage{booktabs}``)."""
    cols = columns(s.metrics)
    keys = s.keys
    marked = [marked_cells(s.stats, s.frame, m, (r"\textbf{", "}"), r"$^\dagger$") for m in cols]
    lines = [r"\begin{table}[t]", r"\centering", r"\small"]
    for part in range(0, max(len(cols), 1), MAX_COLUMNS):
        some = range(part, min(part + MAX_COLUMNS, len(cols)))
        if part:
            lines.append(r"\medskip")
        lines += _tabular(s, keys, [cols[j] for j in some], [marked[j] for j in some])
    lines += [r"\caption{" + (_tex(caption) if caption else
                               r"Mean $\pm$ sample standard deviation over seeds; best mean in "
                               r"bold, $^\dagger$ where it beats every other row paired by seed "
                               r"(95\% Student-t). ade\_vs\_cv: position ADE over constant "
                               r"velocity's (below 1 beats it); ade\_vs\_dnri: over DNRI's on the "
                               r"same seed.") + "}",
              r"\end{table}"]
    return "\n".join(lines) + "\n"


def _tabular(s: Summary, keys: Sequence[str], cols: Sequence[str],
             marked: Sequence[tuple]) -> list[str]:
    """One tabular of the table: the keys, n and the given columns, one row per group."""
    head = [*(_tex(k) for k in keys), "$n$",
            *(_header(m, fmt) for m, (fmt, _) in zip(cols, marked, strict=True))]
    lines = [r"\begin{tabular}{" + "l" * (len(keys) + 1) + "r" * len(cols) + "}",
             r"\toprule", " & ".join(head) + r" \\", r"\midrule"]
    for i, g in enumerate(s.groups):
        row = [("--" if mean == "–" else mean) + (rf" $\pm$ {std}" if std else "")
               for mean, std in (c[i] for _, c in marked)]
        lines.append(" & ".join([*(_tex(g.key.get(k, "")) for k in keys), str(len(g.jobs)), *row])
                     + r" \\")
    return [*lines, r"\bottomrule", r"\end{tabular}"]
