"""Where a soccer model's forecast error comes from: its position ADE over constant velocity's on the validation
windows of experiment=soccer, rolled out with the prior's sampled edges (the default), the prior's most likely
edges, and no edges at all (every pair type 0, no messages). Forecast from the first burn-in frames; the agents
present at the burn-in's last frame carry on.

python docs/journal/soccer_edges.py RUN [RUN ...] --out docs/records/NAME.json   (docs/journal/soccer.md)
(--override KEY=VALUE ...: more overrides of the experiment's data, e.g. the run's own)"""

import argparse
import json

import torch
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate

import dider
import dider.run  # noqa: F401  (registers the kloppy_sample resolver)
from dider.models.baselines import ConstantVelocity

HORIZONS = (1, 10, 20)


def ade(norm, pred, x, mask, burn_in, steps):
    """Mean displacement over frames 1..h after the burn-in, per horizon: pred [B, P, N, 4] normalised."""
    p, t = norm.denormalize(pred)[..., :2], norm.denormalize(x[:, burn_in:burn_in + steps])[..., :2]
    ok = mask[:, burn_in:burn_in + steps] & mask[:, burn_in - 1:burn_in]
    d = (p - t).norm(dim=-1)
    return [(d[:, :h][ok[:, :h]]).sum().item() for h in HORIZONS], [ok[:, :h].sum().item() for h in HORIZONS]


def score(run, split, overrides=()):
    net = dider.load(run).network.eval()
    GlobalHydra.instance().clear()
    with initialize_config_module(version_base="1.3", config_module="dider.conf"):
        cfg = compose(config_name="config", overrides=["experiment=soccer", *overrides])
    dm = instantiate(cfg.data, _convert_="all")
    dm.prepare_data()
    dm.setup("fit")
    burn_in, steps = cfg.protocol.burn_in, max(HORIZONS)
    sums = {k: torch.zeros(len(HORIZONS)) for k in ("sample", "argmax", "none", "cv")}
    counts = torch.zeros(len(HORIZONS))
    for batch in {"val": dm.val_dataloader, "test": dm.test_dataloader}[split]():
        x, mask = batch["states"], batch["mask"]
        n = x.shape[2]
        for mode in sums:
            torch.manual_seed(0)
            with torch.no_grad():
                if mode == "cv":
                    pred = net.forecast_after(x, mask, burn_in, steps, ConstantVelocity())
                elif mode == "none":
                    edges = torch.zeros(x.shape[0], n * (n - 1), burn_in + steps - 1, dtype=torch.long)
                    held = torch.cat([mask[:, :burn_in], mask[:, burn_in - 1:burn_in].expand(-1, steps, -1)], 1)
                    pred = net.rollout(x[:, :burn_in], held, burn_in, steps, edges=edges)[0]
                else:
                    net.rollout_edges = mode
                    pred = net.forecast_after(x, mask, burn_in, steps)
            s, c = ade(dm.normalizer, pred, x, mask, burn_in, steps)
            sums[mode] += torch.tensor(s)
        counts += torch.tensor(c, dtype=torch.float)
    means = {k: (v / counts) for k, v in sums.items()}
    return {mode: {f"h{h:02d}": {"ade_m": round(float(means[mode][i]), 4),
                                 "vs_cv": round(float(means[mode][i] / means["cv"][i]), 4)}
                   for i, h in enumerate(HORIZONS)} for mode in means}


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--split", default="val")
    parser.add_argument("--out", required=True)
    parser.add_argument("--override", nargs="*", default=[], help="more overrides of experiment=soccer")
    args = parser.parse_args()
    more = "".join(f" '{o}'" for o in args.override)
    record = {"command": "python docs/journal/soccer_edges.py " + " ".join(args.runs) + f" --split {args.split}"
                         + (f" --override{more}" if more else ""),
              "runs": {run: score(run, args.split, args.override) for run in args.runs}}
    with open(args.out, "w") as f:
        json.dump(record, f, indent=1)
    print(json.dumps(record, indent=1))
