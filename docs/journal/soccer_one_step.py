"""One-step position error of a trained soccer model against constant velocity, on the training and the test
windows: python docs/journal/soccer_one_step.py RUN_FOLDER (docs/journal/soccer.md)."""

import sys

import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

import dider
import dider.run  # noqa: F401  (registers the kloppy_sample resolver)

# the recipe the run was trained with (docs/journal/soccer.md)
RECIPE = ["data.source.provider=skillcorner", "data.windows.downsample=2", "data.windows.seq_len=30",
          "data.windows.stride=30", "protocol.burn_in=10", "protocol.horizons=[1,10,20]",
          "data.windows.min_agent_steps=15", "data.windows.min_agents=4",
          "data.source.files={meta_data:'${kloppy_sample:skillcorner_match_data.json}',"
          "raw_data:'${kloppy_sample:skillcorner_structured_data.json}'}"]
run = sys.argv[1]
m = dider.load(run)
with initialize_config_module(version_base="1.3", config_module="dider.conf"):
    cfg = compose(config_name="config", overrides=["data=soccer", *RECIPE])
dm = instantiate(cfg.data, _convert_="all")
dm.prepare_data()
dm.setup("fit")
norm = dm.normalizer
torch.manual_seed(0)
for split in ("train", "test"):
    loader = dm._dataloader(split, train=False)
    errs = {"model": [], "cv": []}
    for batch in loader:
        x, mask = batch["states"], batch["mask"]
        for b in (5, 10, 15, 20):
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
