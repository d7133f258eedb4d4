"""Why a protocol seed's posterior interaction runs are long: how many of its runs (``segments.json``, the test pass's
segments of all 500 test clips) are held from a push to the clip's end, and what the per-step posterior and the
decoder's evidence say on the steps after a push that the segment still holds (the tested checkpoint, again on the
test clips).

    python docs/journal/run_on_diagnosis.py multirun/fix_t025_s4 multirun/fix_t025_s3 \
        --out docs/records/run_on_diagnosis.json
"""

from __future__ import annotations

import argparse
import glob
import json
import logging
from pathlib import Path

import numpy as np
import torch

from dider.data.clips import ClipsDataModule
from dider.training.module import RelationalVAEModule


def held_to_end(segments: dict, truth: np.ndarray) -> dict[str, int]:
    """Interaction segments, and those held 10 or more steps past their last true interaction step to the clip's end."""
    total = run_on = 0
    for clip in segments["clips"]:
        for e, edge in enumerate(clip["edges"]):
            true = truth[clip["clip"], :, e]
            for s in edge["segments"]:
                if s["type"] == 0:
                    continue
                total += 1
                inside = np.flatnonzero(true[s["start"]:s["end"]])
                run_on += int(inside.size > 0 and s["end"] - (s["start"] + inside[-1] + 1) >= 10
                              and s["end"] == true.shape[0])
    return {"interaction_segments": total, "held_to_clip_end": run_on}


def after_push(module: RelationalVAEModule, dm: ClipsDataModule) -> dict[str, float]:
    """On edge-steps after an edge's last true interaction step: where the held segment still holds an interaction
    through the clip's end, and where it was released: the per-step posterior's interaction probability and the
    decoder's evidence (nats)."""
    ds, parts = dm.datasets["test"], []
    with torch.no_grad():
        for i in range(0, len(ds), 100):
            batch = ds.__getitems__(list(range(i, min(i + 100, len(ds)))))
            out = module.model.infer(batch, hard=True)
            parts.append((out.probs[..., 1:].sum(-1), out.step_logits.softmax(-1)[..., 1:].sum(-1), out.evidence,
                          batch["edges"].transpose(1, 2) > 0))
    held, step, evidence, truth = (torch.cat(p).numpy() for p in zip(*parts, strict=True))
    steps = np.arange(truth.shape[-1])
    last = np.where(truth.any(-1), truth.shape[-1] - 1 - np.argmax(truth[..., ::-1], -1), -1)
    after = (steps > last[..., None]) & (last[..., None] >= 0)
    out = {}
    held_on = after & (held > 0.5) & (held[..., -1:] > 0.5)
    for name, where in (("held_to_end", held_on), ("released", after & (held <= 0.5))):
        out[name] = {"edge_steps": int(where.sum()), "step_posterior_interaction": float(step[where].mean()),
                     "evidence_median": float(np.median(evidence[where])),
                     "evidence_share_over_0.25": float((evidence[where] >= 0.25).mean())}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="+")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    logging.disable(logging.WARNING)
    dm = ClipsDataModule(source={"reader": "push"}, num_train=10000, num_val=200, num_test=500,
                         loader={"batch_size": 16, "eval_batch_size": 256})  # the protocol's data
    dm.setup()
    truth = (dm.datasets["test"].edges > 0).numpy()
    result = {"command": "python docs/journal/run_on_diagnosis.py " + " ".join(args.folders) + f" --out {args.out}"}
    for folder in args.folders:
        job = Path(glob.glob(f"{folder}/*/metrics.json")[0]).parent
        meta = json.loads((job / "metrics.json").read_text())
        module = RelationalVAEModule.load_from_checkpoint(job / meta["checkpoint"], map_location="cpu").eval()
        result[folder] = {**held_to_end(json.loads((job / "segments.json").read_text()), truth),
                          **after_push(module, dm)}
        print(folder, result[folder], flush=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
