"""A run's results as one Markdown card (TensorBoard's text tab): the forecast in data units against
constant velocity per horizon, the edge recalls, the model's own segments and what each learned type
means, so what the model learned reads at a glance instead of as single-dot curves."""

from __future__ import annotations

import math
import re
from collections.abc import Mapping

from dider.evaluation.scoring import cv_verdict
from dider.evaluation.type_meaning import PAIR_FEATURES, degenerate_types, pair_verdict, profile_rows


def _num(value: float | None) -> str:
    """Four significant digits; a dash for a missing or NaN value."""
    return "–" if value is None or not math.isfinite(value) else f"{value:.4g}"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header),
            *("| " + " | ".join(r) + " |" for r in rows)]


def results_markdown(metrics: Mapping[str, float], title: str = "") -> str:
    """The card of the ``test/`` metrics of a run (``metrics.json``'s ``metrics``)."""
    lines = [f"### {title}" if title else "### Results", ""]
    horizons = sorted({m.group(1) for k in metrics if (m := re.fullmatch(r"test/ade/h(\d+)", k))},
                      key=int)
    if horizons:
        rows = [[f"h{h}", _num(metrics.get(f"test/ade/h{h}")),
                 _num(metrics.get(f"test/cv/ade/h{h}")),
                 _num(metrics.get(f"test/ade_vs_cv/h{h}")), _num(metrics.get(f"test/fde/h{h}")),
                 _num(metrics.get(f"test/cv/fde/h{h}"))] for h in horizons]
        lines += ["**Forecast** (positions, data units, same clips; ratio < 1 beats constant "
                  "velocity)", ""]
        lines += _table(["horizon", "ADE", "constant velocity ADE", "ratio", "FDE",
                         "constant velocity FDE"], rows)
        if verdict := cv_verdict(metrics):
            lines += ["", verdict[0]]
        lines.append("")
    recall = [(k.removeprefix("test/edge_acc/"), v) for k, v in metrics.items()
              if re.fullmatch(r"test/edge_acc/(posterior|prior)/(none|interaction)", k)]
    if recall:
        lines += ["**Edge recall** (against the ground truth)", ""]
        lines += (_table(["edges / class", "recall"], [[k, _num(v)] for k, v in sorted(recall)])
                  + [""])
    cut = {k.rsplit("/", 1)[1]: v for k, v in metrics.items() if k.startswith("test/segments/")}
    if cut:
        lines += ["**The model's own segments**", ""]
        lines += (_table(["", "value"],
                         [[k.replace("_", " "), _num(v)] for k, v in sorted(cut.items())]) + [""])
    if types := profile_rows(dict(metrics), "test"):
        header = ["type", "share", *(f"{f} (others)" for f in PAIR_FEATURES),
                  "against shuffled pairs"]
        rows = [[str(r["type"]), f"{100 * r['share']:.1f}%",
                 *(f"{_num(r[f])} ({_num(r[f'others_{f}'])})" for f in PAIR_FEATURES),
                 pair_verdict(r["beyond_shuffled_distance"], r["beyond_shuffled_closing_speed"])]
                for r in types]
        lines += ["**What each type means** (mean over the edge-steps that hold it; in brackets, "
                  "the others)", ""]
        lines += _table(header, rows)
        if warning := degenerate_types(dict(metrics), "test"):
            lines += ["", warning]
    return "\n".join(lines).rstrip() + "\n"
