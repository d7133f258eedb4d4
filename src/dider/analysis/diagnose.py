"""The loss of given segmentations at a run's trained weights: does the model sit where its own objective
wants it?

    python -m dider.analysis.diagnose RUN [--clips 200] [--draws 4] [--lengths 3,5,10] [--seed 0] [--out FILE]

For the run's test clips, each segmentation below is scored with the trained network, split into the NLL
(per agent-step) and the objective's other terms (the edge KL and the duration KL per edge-step, the sparsity
term where the model has one), and ``loss``, the objective free of schedules (the NLL and each term at its weight,
``weights`` in the output):
- ``own (test)``: the model's own cut as evaluation takes it, with its own duration KL;
- ``own (training)``: the cut the plugin draws in training, with its own duration KL;
- ``one-step``: a segment at every step;
- ``posterior runs``: a segment wherever the per-step posterior's most likely type changes;
- ``truth runs``: a segment wherever the true type changes (data with edge labels);
- ``fixed L``: segments of L steps.
The given cuts (all but ``own``) are scored with the duration KL of a posterior certain of the cut (-log of the
prior's probability of it; 0 for a model without a duration latent), the cut's best case. Every cut also keeps
the boundaries no plugin chooses (the clip's start, the burn-in's end, where an edge enters). The NLL is
averaged over ``--draws`` draws of the edge types. Shapes: B clips, E edges, T-1 transitions.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from dider.evaluation.metrics import switches
from dider.graph import edge_mask
from dider.io import atomic_write_text, read_run_record
from dider.models.vae import RelationalVAE
from dider.outputs.run_record import command_line
from dider.targets import build
from dider.trained import find_checkpoint

STATS = ("segments_per_edge", "steps_per_segment")


def _changes(types: torch.Tensor) -> torch.Tensor:
    """[B, E, T] types -> [B, E, T] bool: a segment starts where the type changes."""
    return torch.nn.functional.pad(switches(types), (1, 0), value=True)


def cuts(net: RelationalVAE, batch: dict[str, torch.Tensor], lengths: Sequence[int]) -> dict[str, torch.Tensor | None]:
    """The given segmentations of a batch, each [B, E, T-1] bool (a segment starts at each true step), by name;
    ``own`` entries are None (the plugin cuts)."""
    x, mask = batch["states"], batch["mask"]
    enc = net.encoder(x, None if bool(mask.all()) else mask)
    b, e, t, _ = enc.h_fwd.shape
    step = torch.arange(t)
    out: dict[str, torch.Tensor | None] = {"own (test)": None, "own (training)": None,
                                           "one-step": torch.ones(b, e, t, dtype=torch.bool),
                                           "posterior runs": _changes(enc.posterior_logits.argmax(-1))}
    if "edges" in batch:
        out["truth runs"] = _changes(batch["edges"].transpose(1, 2))
    for length in lengths:
        out[f"fixed {length}"] = (step % length == 0).expand(b, e, t)
    return out


@torch.no_grad()
def score(net: RelationalVAE, batch: dict[str, torch.Tensor], cut: torch.Tensor | None, draws: int, seed: int,
          training_cut: bool = False) -> dict[str, float]:
    """The objective's terms (batch means) of one segmentation, and ``loss``, its ``nelbo`` (the NLL and each
    term at its weight, no schedule): the plugin's own cut (``cut`` None; drawn as in training with
    ``training_cut``) or a given one, averaged over ``draws`` draws of the types."""
    sums: dict[str, float] = {}
    for draw in range(draws):
        torch.manual_seed(seed + draw)
        net.duration.train(training_cut)
        out = net.infer(batch, hard=True, cut=cut)
        net.duration.eval()
        terms = net.loss(out)  # after training: every schedule at its end (KL weight 1, capacities reached)
        for key, value in terms.items():
            if key != "loss":  # the schedules' loss: the row's loss is the objective without them
                name = "loss" if key == "nelbo" else key
                sums[name] = sums.get(name, 0.0) + float(value) / draws
        if draw == 0:
            present = edge_mask(batch["mask"][:, :-1]).any(1)
            stats = out.seg.stats(present)
    return sums | {"segments_per_edge": float(stats["segments_per_edge"]),
                   "steps_per_segment": float(stats["steps_per_segment"])}


def run_config_file(run: Path) -> Path:
    """The file :func:`run_config` reads."""
    record = run / "metrics.json"
    return record if record.is_file() and "config" in read_run_record(record) else run / ".hydra" / "config.yaml"


def run_config(run: Path) -> DictConfig:
    """A run folder's config: the one its ``metrics.json`` records, else Hydra's ``.hydra/config.yaml``."""
    record, hydra = run / "metrics.json", run / ".hydra" / "config.yaml"
    if record.is_file() and "config" in (saved := read_run_record(record)):
        return OmegaConf.create(saved["config"])
    if hydra.is_file():
        return OmegaConf.load(hydra)
    raise FileNotFoundError(f"{run}: not a run folder (neither {record} with its config nor {hydra}); "
                            "dider.analysis.diagnose reads the run's data and model settings from it")


def diagnose(run: str | Path, clips: int = 200, draws: int = 4, lengths: Sequence[int] = (3, 5, 10),
             seed: int = 0, trust: Collection[str] = ()) -> dict[str, Any]:
    """Score every segmentation on the first ``clips`` test clips of a run folder -> {"rows": {name: terms}}.
    The checkpoint's and the run folder's configs are data: they build dider's classes and the ``trust``-ed ones
    only (:mod:`dider.targets`)."""
    run = Path(run)
    cfg = run_config(run)
    ckpt = find_checkpoint(run)
    net = RelationalVAE.from_checkpoint(ckpt, trust).eval()
    data = OmegaConf.to_container(cfg.data, resolve=True)
    datamodule = build(data, "data", run_config_file(run), "data", trust)
    datamodule.setup("test")
    batches, seen = [], 0
    for batch in datamodule.test_dataloader():
        take = min(clips - seen, batch["states"].shape[0])
        batches.append({k: v[:take] for k, v in batch.items() if isinstance(v, torch.Tensor)})
        seen += take
        if seen >= clips:
            break
    rows: dict[str, dict[str, float]] = {}
    weights = [bt["states"].shape[0] / seen for bt in batches]
    for bt, w in zip(batches, weights, strict=True):
        for name, cut in cuts(net, bt, lengths).items():
            terms = score(net, bt, cut, draws, seed, training_cut=name == "own (training)")
            row = rows.setdefault(name, dict.fromkeys(terms, 0.0))
            for k, v in terms.items():
                row[k] += w * v
    weights = {k: t.weight for k, t in net.objective.terms.items() if k != "nll" and t.in_nelbo}
    return {"run": str(run), "checkpoint": str(ckpt), "clips": seen, "draws": draws, "seed": seed,
            "weights": weights, "rows": rows}


def table(result: dict[str, Any]) -> str:
    """The rows as a plain-text table."""
    first = next(iter(result["rows"].values()), {})
    terms = [k for k in first if k not in (*STATS, "loss")] + ["loss"]
    head = f"{'segmentation':18s} {'slots/edge':>10s} {'steps/slot':>10s} " + " ".join(f"{k:>11s}" for k in terms)
    lines = [head]
    for name, row in result["rows"].items():
        lines.append(f"{name:18s} {row['segments_per_edge']:10.2f} {row['steps_per_segment']:10.2f} "
                     + " ".join(f"{row[k]:11.4f}" for k in terms))
    return "\n".join(lines)


def _lengths(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v]
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"--lengths: expected comma-separated integers, got {text!r}") from err
    if any(v < 1 for v in values):
        raise argparse.ArgumentTypeError(f"--lengths: every length must be >= 1, got {text!r}")
    return values


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m dider.analysis.diagnose", description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="a run folder (with .hydra/config.yaml and a checkpoint)")
    parser.add_argument("--clips", type=int, default=200, help="test clips to score (default 200)")
    parser.add_argument("--draws", type=int, default=4, help="draws of the edge types per clip (default 4)")
    parser.add_argument("--lengths", type=_lengths, default=[3, 5, 10], help="fixed slot lengths (default 3,5,10)")
    parser.add_argument("--seed", type=int, default=0, help="the draws' seed (default 0)")
    parser.add_argument("--out", type=Path, help="write the result as JSON here")
    parser.add_argument("--trust", nargs="+", default=[], metavar="CLASS",
                        help="dotted paths of classes of your own the run's configs may build (a plugin, a source)")
    args = parser.parse_args(argv)
    if args.clips < 1 or args.draws < 1:
        parser.error(f"--clips and --draws must be >= 1, got {args.clips} and {args.draws}")
    result = {"command": command_line(parser.prog, argv)} | diagnose(args.run, args.clips, args.draws, args.lengths,
                                                                   args.seed, args.trust)
    print(table(result))
    if args.out is not None:
        atomic_write_text(args.out, json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
