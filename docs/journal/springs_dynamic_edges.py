"""Where a model's edges on the switching springs lose the truth: the per-step posterior head, the posterior as it is
held over segments (what the model reports; DNRI's is the per-step one), the online prior's per-step head and, where
the objective reads it, the decoder's edge evidence (nats), each scored against the true springs of the test clips by
AUROC, accuracy at 0.5 and its mean on spring / no-spring edge-steps.

python docs/journal/springs_dynamic_edges.py --out docs/records/springs_dynamic_edge_diagnosis.json \
    MODEL=CHECKPOINT ...   (the checkpoint each run tested: the one its val/select chose; --clips: test clips, 500)
"""
import argparse
import json

import torch
from torchmetrics.functional.classification import binary_auroc

import dider
from dider.data.clips import ClipsDataModule
from dider.data.simulators.particles import Simulation


def diagnose(path: str, clips: int = 500, cache: str | None = None) -> dict[str, dict[str, float]]:
    model = dider.load(path)
    net = model.network.eval()
    # experiment=springs_dynamic's test clips (each split draws from its own stream: the training and validation
    # sizes do not change them, and the normaliser is the model's)
    dm = ClipsDataModule(source=Simulation(switch_prob=0.02), num_train=8, num_val=8,
                         num_test=clips, loader={"eval_batch_size": 100}, **({"cache_dir": cache} if cache else {}))
    dm.use_normalizer(model.normalizer)
    dm.setup()
    parts: dict[str, list[torch.Tensor]] = {"truth": [], "per_step": [], "held": [], "prior": [], "evidence": []}
    with torch.no_grad():
        for batch in dm.test_dataloader():
            out = net.infer(batch, hard=False)
            parts["truth"].append(batch["edges"].transpose(1, 2).reshape(-1))  # [B, E, T-1] as the model's
            parts["per_step"].append(out.step_logits.softmax(-1)[..., 1].reshape(-1))
            parts["held"].append(out.probs[..., 1].reshape(-1))
            parts["prior"].append(out.prior_step_logits.softmax(-1)[..., 1].reshape(-1))
            if out.evidence is not None:
                parts["evidence"].append(out.evidence.reshape(-1))
    truth = torch.cat(parts.pop("truth")).long()
    found = {}
    for name, values in parts.items():
        if not values:
            continue
        x = torch.cat(values).float()
        ok = torch.isfinite(x)
        found[name] = {"auroc": float(binary_auroc(x[ok], truth[ok])),
                       "mean_on_spring": float(x[ok & (truth == 1)].mean()),
                       "mean_no_spring": float(x[ok & (truth == 0)].mean())}
        if name != "evidence":
            found[name]["accuracy"] = float(((x > 0.5).long() == truth).float().mean())
    return found


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", required=True)
    parser.add_argument("--clips", type=int, default=500, help="test clips")
    parser.add_argument("--cache", help="the data cache folder (default: the data module's)")
    parser.add_argument("runs", nargs="+", help="MODEL=CHECKPOINT")
    args = parser.parse_args()
    sizes = "" if args.clips == 500 else f" --clips {args.clips}"
    record = {"command": "python docs/journal/springs_dynamic_edges.py --out " + args.out + sizes + " "
                         + " ".join(args.runs),
              "models": {run.split("=", 1)[0]: diagnose(run.split("=", 1)[1], args.clips, args.cache)
                         for run in args.runs}}
    with open(args.out, "w") as f:
        json.dump(record, f, indent=1)
    print(json.dumps(record["models"], indent=1))
