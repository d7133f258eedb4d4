"""The cost of a training step of ``model=dider`` at the standard protocol's sizes (batches of 32 clips of 50 frames,
3 agents, burn-in 25) with the online prior reading the roll-out (``model.net.prior_rollout``, every clip) against
without: forward and backward, fp32, A/B rounds interleaved in one process.

    python docs/journal/prior_rollout_cost.py --rounds 5 --steps 20
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch
from hydra import compose, initialize_config_module

from dider.data.simulate import simulate_push
from dider.models.plugins import Progress
from dider.models.vae import RelationalVAE


def build(rollout: float | None) -> RelationalVAE:
    with initialize_config_module(version_base="1.3", config_module="dider.conf"):
        setting = "null" if rollout is None else rollout
        cfg = compose(config_name="config", overrides=["experiment=synth_protocol", "model=dider",
                                                       f"model.net.prior_rollout={setting}"])
    torch.manual_seed(0)
    return RelationalVAE.from_config(cfg.model).train()


def time_steps(net: RelationalVAE, batch: dict, steps: int) -> float:
    opt = torch.optim.Adam(net.parameters(), 1e-4)
    progress = Progress(5000, 5000)  # the end of training: every clip reads the roll-out where it is on
    start = time.perf_counter()
    for _ in range(steps):
        out = net.infer(batch, False, progress, burn_in=25)
        loss = net.loss(out, progress)["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    return (time.perf_counter() - start) / steps


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=20)
    args = parser.parse_args()
    states, _ = simulate_push(32, 50, 0.05, seed=0)
    batch = {"states": states[:, :50].float(), "mask": torch.ones(32, 50, 3, dtype=torch.bool), "everyone": True}
    nets = {"true frames": build(None), "prior_rollout": build(0.0)}
    times: dict[str, list[float]] = {k: [] for k in nets}
    for net in nets.values():
        time_steps(net, batch, 2)  # warm-up
    for _ in range(args.rounds):
        for name, net in nets.items():
            times[name].append(time_steps(net, batch, args.steps))
    out = {k: {"median_s_per_step": statistics.median(v), "rounds": v} for k, v in times.items()}
    out["ratio"] = out["prior_rollout"]["median_s_per_step"] / out["true frames"]["median_s_per_step"]
    out["threads"] = torch.get_num_threads()
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
