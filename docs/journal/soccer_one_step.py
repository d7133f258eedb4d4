"""One-step position error of a trained soccer model against constant velocity, on the training and the test
windows, after burn-ins of 5, 10, 15 and 20 steps (docs/journal/soccer.md):

python docs/journal/soccer_one_step.py RUN_FOLDER [OVERRIDE ...] [--out RECORD.json]

(OVERRIDE: more overrides of the recipe's data below, e.g. the run's own; --out writes the figures as a record)."""

import argparse
import json
import shlex

import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from torch.utils.data import DataLoader

import dider
import dider.run  # noqa: F401  (registers the kloppy_sample resolver)

# the recipe the run was trained with (docs/journal/soccer.md)
RECIPE = ["data.source.provider=skillcorner", "data.windows.downsample=2", "data.windows.seq_len=30",
          "data.windows.stride=30", "protocol.burn_in=10", "protocol.horizons=[1,10,20]",
          "data.windows.min_agent_steps=15", "data.windows.min_agents=4",
          "data.source.files={meta_data:'${kloppy_sample:skillcorner_match_data.json}',"
          "raw_data:'${kloppy_sample:skillcorner_structured_data.json}'}"]
BURN_INS = (5, 10, 15, 20)


def one_step(run: str, overrides: list[str] = ()) -> dict[str, dict[str, float]]:
    """split -> the mean one-step position error (metres) of the model's forecast and of constant velocity, over the
    agents present at the step and the two before, and their ratio."""
    m = dider.load(run)
    with initialize_config_module(version_base="1.3", config_module="dider.conf"):
        cfg = compose(config_name="config", overrides=["data=soccer", *RECIPE, *overrides])
    dm = instantiate(cfg.data, _convert_="all")
    dm.prepare_data()
    dm.setup("fit")
    norm = dm.normalizer
    torch.manual_seed(0)
    found = {}
    for split in ("train", "test"):  # every window of the split, in order
        loader = DataLoader(dm.datasets[split], batch_size=dm.loader.eval_batch_size, shuffle=False,
                            collate_fn=dm.collate_fn)
        errs = {"model": [], "cv": []}
        for batch in loader:
            x, mask = batch["states"], batch["mask"]
            for b in BURN_INS:
                with torch.no_grad():
                    pred = m.network.forecast_after(x, mask, b, 1)[:, 0]  # [B, N, 4]
                raw = norm.denormalize(x)
                p = norm.denormalize(pred)[..., :2]
                truth = raw[:, b, :, :2]
                cv = raw[:, b - 1, :, :2] * 2 - raw[:, b - 2, :, :2]
                ok = mask[:, b] & mask[:, b - 1] & mask[:, b - 2]
                errs["model"].append((p - truth).norm(dim=-1)[ok])
                errs["cv"].append((cv - truth).norm(dim=-1)[ok])
        mo, cv = torch.cat(errs["model"]).mean().item(), torch.cat(errs["cv"]).mean().item()
        print(f"{split}: one-step position error model {mo:.3f} m, constant velocity {cv:.3f} m, ratio {mo/cv:.2f}")
        found[split] = {"model_m": round(mo, 3), "constant_velocity_m": round(cv, 3), "ratio": round(mo / cv, 2)}
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="a run folder or a checkpoint")
    parser.add_argument("overrides", nargs="*", help="more overrides of the recipe's data")
    parser.add_argument("--out", help="write the figures here as a record")
    args = parser.parse_args()
    found = one_step(args.run, args.overrides)
    if args.out:
        command = ["python", "docs/journal/soccer_one_step.py", args.run, *args.overrides, "--out", args.out]
        record = {"command": shlex.join(command),
                  "what": "mean one-step position error (metres) after burn-ins of "
                          + ", ".join(map(str, BURN_INS[:-1])) + f" and {BURN_INS[-1]} steps, of the model's "
                          "forecast and of constant velocity, over the agents present at the step and the two before",
                  **found}
        with open(args.out, "w") as f:
            json.dump(record, f, indent=2)


if __name__ == "__main__":
    main()
