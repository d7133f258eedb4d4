"""What a run learned, in a few plain lines printed at its end: the forecast against constant
velocity (and what the shipped trained model of the same kind and data scores on its own test
clips), what each edge type means, a few edges' segments as text timelines beside the truth, and
where to look next.

The lines read a finished run's own outputs (its test metrics and ``clips.npz``); nothing is
computed again.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from dider.evaluation.scoring import edges_help
from dider.evaluation.type_meaning import profile_notes

# A timeline's characters: "." no interaction, "1".."9" a type, " " the edge absent.
MARKS = " .123456789"


def timeline(types: np.ndarray) -> str:
    """[T] int (-1 absent, 0 none, k > 0 a type) -> one character per step."""
    return "".join(MARKS[min(int(k), 9) + 1] for k in types)


def example_edges(path: Path, count: int = 3) -> list[str]:
    """Text timelines of the ``count`` edges of ``clips.npz`` whose true type changes most often (or
    whose segments do, without a truth): the model's segments above the truth, each line a step per
    character."""
    if not path.is_file():
        return []
    with np.load(path, allow_pickle=False) as arrays:
        segments = arrays["segments"]  # [S, E, T-1]
        truth = arrays["truth"] if "truth" in arrays else None
    n = int(round((1 + math.sqrt(1 + 4 * segments.shape[1])) / 2))
    send, recv = np.nonzero(~np.eye(n, dtype=bool))
    busy = truth if truth is not None else segments
    changes = (np.diff(busy, axis=-1) != 0).sum(-1)  # [S, E]
    order = np.argsort(-changes, axis=None, kind="stable")[:count]
    lines = []
    for flat in order:
        clip, edge = np.unravel_index(flat, changes.shape)
        head = f"  clip {clip}, agent {send[edge]} -> {recv[edge]}:"
        lines.append(f"{head:32s} model {timeline(segments[clip, edge])}")
        if truth is not None:
            lines.append(f"{'':32s} truth {timeline(truth[clip, edge])}")
    return lines


def forecast_lines(metrics: Mapping[str, float], horizons: Sequence[int], units: str | None,
                   reference: Mapping[str, float] | None = None,
                   reference_name: str = "") -> list[str]:
    """The forecast in data units at each horizon against constant velocity's (and a reference
    model's)."""
    unit = f" {units}" if units else ""
    lines = []
    for h in horizons:
        ade, cv = metrics.get(f"test/ade/h{h:02d}"), metrics.get(f"test/cv/ade/h{h:02d}")
        if ade is None or cv is None or not (math.isfinite(ade) and math.isfinite(cv)):
            continue
        verdict = "better than" if ade < cv else "no better than"
        line = (f"  {h} step(s) ahead: off by {ade:.3g}{unit} on average, constant velocity by "
                f"{cv:.3g}{unit} ({verdict} it, {ade / cv:.2f}x)")
        if reference and (ref := reference.get(f"test/ade/h{h:02d}")) is not None:
            line += (f"; the shipped {reference_name}: {ref:.3g}{unit}, "
                     f"{reference[f'test/ade_vs_cv/h{h:02d}']:.2f}x")
        lines.append(line)
    return lines


def plain_summary(metrics: Mapping[str, float], horizons: Sequence[int], run: Path,
                  units: str | None = None, reference: Mapping[str, float] | None = None,
                  reference_name: str = "", budget_note: str | None = None) -> str:
    """The summary's text. metrics: the run's test metrics; run: its folder (``clips.npz``, the
    explorer); reference: the test metrics of a shipped model of the same kind (on its own test
    clips); budget_note: one line on how long a run that beats constant velocity takes, printed when
    this one does not."""
    lines = ["What this run learned", "", "Forecast (position error over the test clips' future):"]
    lines += (forecast_lines(metrics, horizons, units, reference, reference_name)
              or ["  (no forecast scored)"])
    longest = max(horizons) if horizons else None
    ratio = metrics.get(f"test/ade_vs_cv/h{longest:02d}") if longest else None
    if ratio is not None and math.isfinite(ratio) and ratio >= 1 and budget_note:
        lines.append(f"  It does not beat constant velocity: {budget_note}")
    if ((edges := metrics.get(f"test/ade_vs_no_edges/h{longest:02d}")) is not None
        and math.isfinite(edges)):
        word = "help" if edges_help(edges) else "do not help"
        lines.append(f"  Its edges {word}: with every edge off its error is {1 / edges:.2f}x what "
                     "it is with them.")
    rows, k = [], 0
    while f"test/type{k}/share" in metrics:
        rows.append(k)
        k += 1
    if rows:
        from dider.evaluation.type_meaning import profile_array

        lines += ["", "What each edge type means (while it holds; others: the other edge-steps):"]
        profile = profile_array(dict(metrics), "test")
        lines += [f"  type {i}: {note}" for i, note in enumerate(profile_notes(profile))]
    if timelines := example_edges(run / "clips.npz"):
        lines += ["", "Example edges, a step per character (. no interaction, 1-9 a type):",
                  *timelines]
    lines += ["", "Where to look next:", f"  python -m dider.analysis.explore {run}   (paths, "
                                         "edges by type, forecast)",
              f"  tensorboard --logdir {run}"]
    return "\n".join(lines)


def shipped_reference(model: str, data: str | None) -> tuple[dict[str, float] | None, str,
                                                             str | None]:
    """The shipped model of the same kind and data (``dider.pretrained()``, e.g. ``synth/dider``):
    its recorded test metrics, its name with how it was trained, and a line on what it takes to
    train one; (None, "", None) if none."""
    from dider.shipped import catalog

    name = f"{data}/{model}"
    record = catalog().get(name)
    if record is None:
        return None, "", None
    how = f"{name} (trained with `{record['trained_with']}`, on its own test clips)"
    took, device = record.get("trained_wall_s"), record.get("trained_device")
    took = (f", {max(1, round(took / 60))} minute(s)"
            + (f" on a {device.upper()}" if device else "") if took else "")
    note = (f"this run is short; the shipped {name} was trained with "
            f"`{record['trained_with']}`{took} (`python -m dider.run mode=eval ckpt_path={name} "
            f"{' '.join(record['evaluate'])}` scores it).")
    return record["metrics"], how, note


def run_summary(metrics: Mapping[str, float], run: Path, model: str, data: str | None,
                units: str | None) -> str:
    """:func:`plain_summary` with the horizons the metrics hold and the shipped model of the same
    kind and data."""
    horizons = sorted({int(k.rsplit("/h", 1)[1]) for k in metrics if k.startswith("test/ade/h")})
    reference, name, note = shipped_reference(model, data)
    return plain_summary(metrics, horizons, run, units, reference, name, note)
