"""Where a positive-control model holds its interaction type, edge by edge, on 200 test clips of the step push
(seed 1): the held rate beside the truth's, the pair's distance and the receiver's acceleration while held.
`python docs/journal/control_held.py RUN [RUN ...]` (run folders; a checkpoint whose objective spelt
`weighting: backed`, a name the setting had before it landed, is read as `backed_share`)."""

import glob
import sys

import torch
from omegaconf import DictConfig, OmegaConf

import dider
from dider.data.clips import ClipsDataModule
from dider.graph import edge_index

LOADER = {"batch_size": 16, "eval_batch_size": 256}  # data=synth's loader


def renamed(o):
    """The checkpoint's hyper-parameters with `weighting: backed` read as `backed_share`."""
    if isinstance(o, dict):
        return {k: "backed_share" if (k == "weighting" and v == "backed") else renamed(v) for k, v in o.items()}
    return o


def load(run: str):
    ckpt = torch.load(sorted(glob.glob(f"{run}/checkpoints/epoch_*.ckpt"))[-1], map_location="cpu", weights_only=False)
    hp = ckpt["hyper_parameters"]
    ckpt["hyper_parameters"] = renamed(OmegaConf.to_container(hp) if isinstance(hp, DictConfig) else hp)
    torch.save(ckpt, "/tmp/control_held.ckpt")
    return dider.load("/tmp/control_held.ckpt")


def main() -> None:
    torch.set_num_threads(1)
    send, recv = edge_index(3)
    for run in sys.argv[1:]:
        model = load(glob.glob(run)[0].rstrip("/"))
        dm = ClipsDataModule(source={"reader": "push", "seed": 1, "push": "step"}, num_train=32, num_val=8,
                             num_test=200, cache_dir="/tmp/leads_cache", loader=LOADER)
        dm.use_normalizer(model.normalizer)
        dm.setup()
        test = dm.datasets["test"]
        batch = test.__getitems__(list(range(len(test))))
        with torch.no_grad():
            held = model.network.eval().infer(batch, hard=True).posterior_types() > 0  # [B, E, T-1]
        truth = batch["edges"].transpose(1, 2) > 0  # [B, T-1, E] -> [B, E, T-1]
        x = model.normalizer.denormalize(batch["states"])  # data units: the push radius is 1
        dist = (x[:, :-1, send, :2] - x[:, :-1, recv, :2]).norm(dim=-1).transpose(1, 2)  # [B, E, T-1]
        accel = (x[:, 1:, :, 2:] - x[:, :-1, :, 2:]).norm(dim=-1)[:, :, recv].transpose(1, 2)
        recall, none = (held & truth).sum() / truth.sum(), (~held & ~truth).sum() / (~truth).sum()
        print(run, f"held {held.float().mean():.3f}, truth {truth.float().mean():.3f}, recall {recall:.3f}, "
              f"none recall {none:.3f}")
        for e in range(len(send)):
            h = held[:, e]
            while_held = (f"distance {dist[:, e][h].mean():.3f}, receiver acceleration {accel[:, e][h].mean():.4f}"
                          if h.any() else "never held")
            print(f"  {send[e]}->{recv[e]}: held {h.float().mean():.3f}, truth {truth[:, e].float().mean():.3f}; "
                  f"{while_held} (otherwise {dist[:, e][~h].mean():.3f}, {accel[:, e][~h].mean():.4f})")


if __name__ == "__main__":
    main()
