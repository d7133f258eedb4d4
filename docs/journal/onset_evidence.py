"""What the decoder's evidence (MarkovDecoder.edge_evidence) is on the true interaction steps, by their position in
the true run (0: the onset), and on the true "none" steps, with the share below the indifference prior's threshold
and the share the posterior holds as an interaction; and the same for the interaction steps the posterior misses.
Read against a model trained with the prior, it says what a lower threshold would leave uncharged.

python docs/journal/onset_evidence.py --model RUN --out docs/records/onset_evidence_indifference.json
"""

import json

import torch
from protocol_clips import clips_from_command_line


def shares(evidence: torch.Tensor, held: torch.Tensor | None = None) -> dict[str, float]:
    out = {"n": int(evidence.numel()), "evidence_median": float(evidence.median())}
    out |= {f"below_{t}": float((evidence < t).float().mean()) for t in (0.1, 0.25, 1.0)}
    return out | ({} if held is None else {"held": float(held.float().mean())})


def main() -> None:
    args, _, net, batch = clips_from_command_line(__doc__.splitlines()[0])
    truth = batch["edges"].transpose(1, 2) > 0  # [B, E, T-1]
    torch.manual_seed(0)
    with torch.no_grad():
        out = net.infer(batch, hard=True)
    if out.evidence is None:
        raise SystemExit(f"{args.model}: its objective has no term that reads the edge evidence")
    ev, held = out.evidence, out.posterior_types() > 0
    pos, run = torch.zeros_like(truth, dtype=torch.long), torch.zeros(truth.shape[:2], dtype=torch.long)
    for t in range(truth.shape[2]):  # each true interaction step's place in its run
        run = torch.where(truth[..., t], run + 1, torch.zeros_like(run))
        pos[..., t] = run - 1
    res = {"command": f"python docs/journal/onset_evidence.py --model {args.model} --out {args.out}",
           "clips": args.clips}
    for p in range(6):
        m = truth & (pos == p)
        res[f"interaction_step_{p}"] = shares(ev[m], held[m])
    m = truth & (pos >= 6)
    res["interaction_step_6_on"] = shares(ev[m], held[m])
    missed = truth & ~held
    res["missed"] = shares(ev[missed]) | {"at_steps_0_1": float((pos[missed] <= 1).float().mean()),
                                          "at_steps_6_on": float((pos[missed] >= 6).float().mean())}
    res["true_none"] = shares(ev[~truth & out.present])
    with open(args.out, "w") as f:
        json.dump(res, f, indent=1)
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
