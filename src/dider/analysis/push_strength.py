"""Which pushes a trained model finds: interaction recall on the synthetic push set by the push's distance.

Particle 2 is pushed by particle i with a force push_factor * (1 - d) while their distance d is below the
radius (1), so a push near the radius barely moves anything: at d > 0.8 the force is under a fifth of its
maximum, and about 45% of the pushes' steps lie there (the bins' step counts in
``docs/records/push_strength_claims_fp32.json``). Edge recall over all push steps mixes those
near-invisible steps with the clear ones; this tool splits it by d, for the posterior (the segments
inferred from whole clips) and the online prior (past only)::

    python -m dider.analysis.push_strength RUN_OR_CKPT [RUN_OR_CKPT ...] [--clips 400] [--seed 4242] \\
        [--bins 0,0.5,0.7,0.8,0.9,1] [--out recall_by_distance.json]

The JSON holds the command (``command``) and one row per run (``runs``).

Fresh clips are simulated with the run's ``push_factor`` (``--seed`` picks them), so any synthetic run can be
scored without its data cache. Shapes: S clips, T frames, E = 6 directed edges.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from dider.data.simulators.push import EDGE_0_TO_2, EDGE_1_TO_2, simulate_push
from dider.evaluation.metrics import EdgeAccuracy
from dider.io import atomic_write_text
from dider.outputs.run_record import command_line
from dider.trained import load

DEFAULT_BINS = (0.0, 0.5, 0.7, 0.8, 0.9, 1.0)


def push_distances(states: torch.Tensor) -> torch.Tensor:
    """Raw simulator states [S, T, 3, 4] -> [S, E, T-1]: for transition t -> t+1 of the edges (0, 2) and
    (1, 2), the distance between the two particles at frame t (what sets the push that produces x_{t+1});
    NaN on the other edges, which never push."""
    pos = states[:, :-1, :, :2]  # [S, T-1, 3, 2]
    dist = torch.full((states.shape[0], 6, states.shape[1] - 1), math.nan, dtype=states.dtype)
    dist[:, [EDGE_0_TO_2, EDGE_1_TO_2]] = (pos[:, :, 2:3] - pos[:, :, :2]).norm(dim=-1).transpose(1, 2)
    return dist


def recall_by_distance(types: torch.Tensor, truth: torch.Tensor, dist: torch.Tensor,
                       bins: Sequence[float] = DEFAULT_BINS) -> list[dict[str, float]]:
    """Interaction recall per distance bin [lo, hi): types, truth [S, E, T-1] long, dist [S, E, T-1] ->
    one row per bin with ``lo``, ``hi``, ``steps`` (true push steps in the bin) and ``recall`` (NaN if none)."""
    if types.shape != truth.shape or dist.shape != truth.shape:
        raise ValueError(f"recall_by_distance: types {tuple(types.shape)}, truth {tuple(truth.shape)} and dist "
                         f"{tuple(dist.shape)} must have one shape")
    pushed = truth > 0
    rows = []
    for lo, hi in itertools.pairwise(bins):
        keep = pushed & (dist >= lo) & (dist < hi)
        metric = EdgeAccuracy()
        metric.update(types, truth, keep)
        rows.append({"lo": float(lo), "hi": float(hi), "steps": int(keep.sum()), "recall": float(metric.compute()[1])})
    return rows


def score(path: str | Path, clips: int = 400, seed: int = 4242, bins: Sequence[float] = DEFAULT_BINS) -> dict[str, Any]:
    """Score one trained synthetic run (a run folder or checkpoint) on ``clips`` fresh clips."""
    model = load(path)
    if model.data_setting("push_factor") is None:
        raise ValueError(f"{path}: not trained on the synthetic push set (data=synth): its data settings "
                         f"(source: {sorted(model.data.get('source') or {})}) have no push_factor")
    states, edges = simulate_push(clips, int(model.data_setting("num_steps")), float(model.data_setting("push_factor")),
                                  seed=seed)
    x = model.normalizer.normalize(states)
    mask = torch.ones(x.shape[:3], dtype=torch.bool)
    said = model.describe(x, mask)  # argmax types in eval mode: no random draw
    truth = edges[:, 1:].transpose(1, 2)  # transition t -> t+1 is labelled edges[t+1]
    dist = push_distances(states.double())
    out: dict[str, Any] = {"run": str(path), "checkpoint": str(model.path), "clips": clips, "seed": seed}
    for key in ("segments", "prior"):
        out[key] = recall_by_distance(said[key], truth, dist, bins)
        overall = EdgeAccuracy()
        overall.update(said[key], truth)
        out[f"{key}_none_recall"] = float(overall.compute()[0])
    return out


def _bins(text: str) -> list[float]:
    try:
        bins = [float(v) for v in text.split(",")]
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"--bins: expected comma-separated numbers, got {text!r}") from err
    if len(bins) < 2 or any(hi <= lo for lo, hi in itertools.pairwise(bins)):
        raise argparse.ArgumentTypeError(f"--bins: expected at least two increasing numbers, got {text!r}")
    return bins


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(prog="python -m dider.analysis.push_strength",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="run folders or checkpoints of models trained on data=synth")
    parser.add_argument("--clips", type=int, default=400, help="fresh clips to simulate (default 400)")
    parser.add_argument("--seed", type=int, default=4242, help="the clips' simulator seed (default 4242)")
    parser.add_argument("--bins", type=_bins, default=list(DEFAULT_BINS),
                        help="distance bin edges (default %(default)s)")
    parser.add_argument("--out", type=Path, help="write the rows as JSON here")
    args = parser.parse_args(argv)
    results = [score(run, args.clips, args.seed, args.bins) for run in args.runs]
    for res in results:
        print(res["run"])
        for key in ("segments", "prior"):
            cells = "  ".join(f"[{r['lo']:g},{r['hi']:g}) {r['recall']:.2f} ({r['steps']})" for r in res[key])
            print(f"  {key:8s} {cells}  none recall {res[f'{key}_none_recall']:.3f}")
    if args.out is not None:
        record = {"command": command_line(parser.prog, argv), "runs": results}
        atomic_write_text(args.out, json.dumps(record, indent=1))
    return results


if __name__ == "__main__":
    main()
