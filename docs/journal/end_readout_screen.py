"""Where evaluation reads a segment's end, screened on trained checkpoints of the standard protocol (no retraining).

Each seed's tested checkpoint is tested again on the same 500 test clips with the end read three ways: ``threshold``
(the first candidate whose posterior hazard passes 0.5, else the clip's end: the shipped readout), ``mode`` (the
mode of q(end)), ``hybrid`` (the threshold's end, or q(end)'s mode where no candidate passes and the segment would
run to the clip's end) and ``hybrid_held`` (the hybrid for segments that hold an interaction only: a "none" segment
that no hazard ends runs to the clip's end). Every readout cuts with all starts at once (``sync_free``), which reads
the same ends as the CPU's segment-by-segment cut. Sampled futures are off (``samples=0``); everything else is the
run's test pass.

    python docs/journal/end_readout_screen.py multirun/fix_t025_s4 multirun/fix_t025_s3 multirun/fix_t025_s2 \
        multirun/indiff_t025_s1 --out docs/records/end_readout_screen.json
"""

from __future__ import annotations

import argparse
import glob
import json
import logging
from pathlib import Path

import lightning as L
import torch

import dider.models.segment_end as segment_end
from dider.data.clips import ClipsDataModule
from dider.models.end_categorical import decided_end, end_log_probs
from dider.training.module import RelationalVAEModule

KEYS = ("test/run_length/posterior", "test/run_length/truth", "test/segments/boundary_f1",
        "test/segments/per_constant_edge", "test/edge_acc/posterior/none", "test/edge_acc/posterior/interaction",
        "test/mse_posterior/h15", "test/mse_posterior/h25")


def hybrid(logits: torch.Tensor, start: torch.Tensor, fixed: torch.Tensor, value: torch.Tensor,
           threshold: float = 0.5) -> torch.Tensor:
    """The decided end, or q(end)'s mode where no candidate decides it (the segment would run to the clip's end)."""
    end = decided_end(logits, start, fixed, value, threshold)
    mode = end_log_probs(logits, start, fixed, value).argmax(-1)
    return torch.where(end >= logits.shape[-1], mode, end)


HELD: dict[str, torch.Tensor] = {}  # "interaction": [B, E, S] whether the segment starting at each step holds one
_every_start = segment_end.SegmentEnd._every_start


def every_start_noting_types(self, feats, steps, types, fixed, value, *rest):  # noqa: ANN001, ANN002, ANN201
    """The plugin's cut with all starts at once, noting the type each start's segment holds (read at its start)."""
    HELD["interaction"] = types[..., 1:].sum(-1) > 0.5
    return _every_start(self, feats, steps, types, fixed, value, *rest)


def hybrid_held(logits: torch.Tensor, start: torch.Tensor, fixed: torch.Tensor, value: torch.Tensor,
                threshold: float = 0.5) -> torch.Tensor:
    """The hybrid's end for a segment holding an interaction; the decided end (or the clip's end) for a "none" one."""
    end = decided_end(logits, start, fixed, value, threshold)
    mode = end_log_probs(logits, start, fixed, value).argmax(-1)
    return torch.where((end >= logits.shape[-1]) & HELD["interaction"], mode, end)


segment_end.SegmentEnd._every_start = every_start_noting_types
READOUTS = {  # name -> (the plugin's end_readout, the functions segment_end calls for it)
    "threshold": ("threshold", {"decided_end": decided_end}),
    "mode": ("median", {"median_end": lambda log_q: log_q.argmax(-1)}),
    "hybrid": ("threshold", {"decided_end": hybrid}),
    "hybrid_held": ("threshold", {"decided_end": hybrid_held}),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="+", help="protocol sweep folders of one job each")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    logging.disable(logging.WARNING)
    originals = {name: getattr(segment_end, name) for name in ("decided_end", "median_end")}
    out = {"command": "python docs/journal/end_readout_screen.py " + " ".join(args.folders) + f" --out {args.out}",
           "results": {}}
    for folder in args.folders:
        record = Path(glob.glob(f"{folder}/*/metrics.json")[0])
        meta = json.loads(record.read_text())
        for name, (readout, patch) in READOUTS.items():
            for attr, fn in {**originals, **patch}.items():
                setattr(segment_end, attr, fn)
            module = RelationalVAEModule.load_from_checkpoint(record.parent / meta["checkpoint"], map_location="cpu")
            module.hparams.samples = 0
            module.model.duration.end_readout = readout
            module.model.duration.sync_free = True
            dm = ClipsDataModule(source={"reader": "push"}, num_train=10000, num_val=200, num_test=500,
                                 loader={"batch_size": 16, "eval_batch_size": 250})
            trainer = L.Trainer(accelerator="cpu", max_epochs=16, logger=False, enable_progress_bar=False,
                                enable_model_summary=False)
            metrics = trainer.test(module, datamodule=dm, verbose=False)[0]
            out["results"].setdefault(folder, {})[name] = {k: float(metrics[k]) for k in KEYS if k in metrics}
            print(folder, name, {k.removeprefix("test/"): round(v, 4) for k, v in out["results"][folder][name].items()},
                  flush=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
