"""Does the loss's gradient on the posterior's edge logits point at the true springs early in training? For NRI
(model=nri_uniform) on experiment=springs_nri's data, with the decoder's type 0 sending messages (skip_first=false)
and silent (skip_first=true): the AUROC of -d loss / d (logit_1 - logit_0), summed over each edge's steps, against
the edge's true spring, every 10 of the first 40 Adam steps (256 clips, batch 32, seed 0).

python docs/journal/springs_gradient.py --out docs/records/springs_gradient.json   (docs/journal/springs.md)
(--clips, --batch, --steps and --every change those sizes: the record's are the defaults)"""

import argparse
import json
import sys

import torch
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate
from torchmetrics.functional.classification import binary_auroc

from dider.models.vae import RelationalVAE


def alignment(skip_first: bool, cache: str, steps: int = 40, clips: int = 256, batch_size: int = 32,
              every: int = 10) -> list[dict[str, float]]:
    GlobalHydra.instance().clear()
    with initialize_config_module(version_base="1.3", config_module="dider.conf"):
        cfg = compose("config", overrides=["experiment=springs_nri", "model=nri_uniform", "hydra.mode=RUN",
                                           f"model.net.decoder.skip_first={str(skip_first).lower()}",
                                           f"data.num_train={clips}", "data.num_val=8", "data.num_test=8",
                                           f"data.cache_dir={cache}"])
    dm = instantiate(cfg.data, _convert_="all")
    dm.setup()
    torch.manual_seed(0)
    model = RelationalVAE.from_config(cfg.model)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.model.optimizer.lr)
    train = dm.datasets["train"]
    batches = [train.__getitems__(list(range(i, min(i + batch_size, len(train)))))
               for i in range(0, len(train), batch_size)]
    rows = []
    for step in range(steps + 1):
        batch = batches[step % len(batches)]
        out = model.infer(batch, hard=False)
        out.step_logits.retain_grad()
        loss = model.loss(out)["loss"]
        opt.zero_grad()
        loss.backward()
        if step % every == 0:
            g = out.step_logits.grad  # [B, E, T-1, 2]
            toward_spring = -(g[..., 1] - g[..., 0]).sum(-1).flatten()
            truth = (batch["edges"][:, 0] > 0).flatten().long()
            auroc = float(binary_auroc(toward_spring, truth))
            rows.append({"step": step, "loss": float(loss.detach()), "gradient_auroc": auroc})
        opt.step()
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--cache", default="/tmp/springs_gradient_cache")
    parser.add_argument("--clips", type=int, default=256, help="training clips")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--steps", type=int, default=40, help="Adam steps")
    parser.add_argument("--every", type=int, default=10, help="steps between the rows")
    args = parser.parse_args()
    torch.set_num_threads(1)
    record = {"command": "python " + " ".join(sys.argv),
              "runs": {f"skip_first={s}": alignment(s, args.cache, args.steps, args.clips, args.batch, args.every)
                       for s in (False, True)}}
    with open(args.out, "w") as f:
        json.dump(record, f, indent=1)


if __name__ == "__main__":
    main()
