"""What the likelihood says about the steps where DIDER's posterior holds an interaction the truth does not have
(the posterior's runs are twice the truth's length at the standard protocol): for each edge-step, the decoder's NLL
of the receiver's next state with that edge at type 0 (none) minus with it at type 1 (interaction), the other edges
as the posterior holds them, in nats (> 0: the decoder prefers the interaction there). Split by what the posterior
and the truth say, and, for the over-held steps, by the pair's distance (the push acts within distance 1, growing
linearly from 0 at the radius).

The whole-clip protocol model (experiment=synth_protocol seed 1 model.net.encoder.posterior_reads=sequence, shipped
as synth/dider up to commit e75a98d), its test clips regenerated (seed 1), the posterior's hard edges (argmax of
each segment), fp32.

git show e75a98d:src/dider/shipped/synth_dider.ckpt > /tmp/whole_clip.ckpt
python docs/journal/overheld.py --model /tmp/whole_clip.ckpt --out docs/records/overheld_protocol.json"""

import argparse
import json
import sys

import torch
from protocol_clips import protocol_clips

from dider.graph import edge_index

BINS = (0.0, 0.8, 1.0, 1.1, 1.25, 1.5, float("inf"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--model", default="synth/dider", help="a shipped name, a run folder or a checkpoint")
    parser.add_argument("--clips", type=int, default=500)
    parser.add_argument("--cache", default="/tmp/overheld_cache")
    args = parser.parse_args()
    model, net, batch = protocol_clips(args.model, args.clips, args.cache)
    torch.manual_seed(0)
    with torch.no_grad():
        out = net.infer(batch, hard=True)
        post = out.posterior_types()  # [B, E, T-1]
        x, k = batch["states"], net.num_types
        z = torch.nn.functional.one_hot(post, k).float().transpose(1, 2)  # [B, T-1, E, K]
        var = net.objective.terms["nll"].variance
        target = x[:, 1:]

        def nll(zz: torch.Tensor) -> torch.Tensor:  # [B, T-1, N]: each agent's next-state NLL (constants dropped)
            return (0.5 * (net.decoder(x[:, :-1], zz) - target).square() / var).sum(-1)

        n = x.shape[2]
        send, recv = edge_index(n)
        gain = torch.empty_like(post, dtype=torch.float32)  # [B, E, T-1]
        for e in range(len(send)):  # edge e set at every step at once: a step's NLL reads that step's z only
            nats = []
            for kind in (0, 1):
                zz = z.clone()
                zz[:, :, e] = torch.nn.functional.one_hot(torch.tensor(kind), k).float()
                nats.append(nll(zz)[:, :, recv[e]])
            gain[:, e] = nats[0] - nats[1]
    truth = batch["edges"].transpose(1, 2)  # [B, E, T-1]
    pos = model.normalizer.denormalize(x)[..., :2]
    dist = (pos[:, :-1, send] - pos[:, :-1, recv]).norm(dim=-1).transpose(1, 2)  # [B, E, T-1], before the step
    groups = {"over-held (posterior interaction, truth none)": (post > 0) & (truth == 0),
              "found (both interaction)": (post > 0) & (truth > 0),
              "missed (posterior none, truth interaction)": (post == 0) & (truth > 0),
              "none (both none)": (post == 0) & (truth == 0)}
    record = {"command": "python " + " ".join(sys.argv), "clips": batch["states"].shape[0], "groups": {},
              "over_held_by_distance": {}}
    for name, sel in groups.items():
        g = gain[sel]
        record["groups"][name] = {"edge_steps": int(sel.sum()), "mean_nats": float(g.mean()),
                                  "median_nats": float(g.median()), "share_below_0.1_nats": float((g.abs() < 0.1)
                                                                                                 .float().mean())}
    over = groups["over-held (posterior interaction, truth none)"]
    for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
        sel = over & (dist >= lo) & (dist < hi)
        if sel.any():
            record["over_held_by_distance"][f"[{lo}, {hi})"] = {"edge_steps": int(sel.sum()),
                                                                "mean_nats": float(gain[sel].mean())}
    with open(args.out, "w") as f:
        json.dump(record, f, indent=1)
    print(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
