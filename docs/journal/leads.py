"""Where DIDER's over-held interaction steps are, and what its objective says about them, at a trained model's weights.

For each held interaction run of the posterior (the model's own cut, evaluation's readout) that overlaps a true
interaction: how many steps before the truth's onset it starts (its lead) and after the truth's end it stops; the
over-held steps split into leads, tails and runs that overlap no true interaction; where the runs start (the clip's
first step and the burn-in's end are boundaries no segment pays for). Then the objective (each term at its weight,
no schedule, as `nelbo`) of the model's own cut against the same cut with every lead cut off: the run started at
the true onset (a boundary there, the type forced to interaction) and the steps before it held at none (the types
at the free boundaries before it forced to none). A negative difference means the objective prefers the trimmed
cut that the model did not find.

python docs/journal/leads.py --model /tmp/whole_clip.ckpt --out docs/records/leads_protocol.json   (the whole-clip
    seed-1 model, shipped as synth/dider up to commit e75a98d: git show e75a98d:src/dider/shipped/synth_dider.ckpt)
python docs/journal/leads.py --model RUN/checkpoints/last.ckpt --out ...
"""

import json
import sys

import torch
import torch.nn.functional as F
from protocol_clips import clips_from_command_line


def runs(mask: torch.Tensor) -> list[tuple[int, int]]:
    """[T] bool -> the (first, last) steps of its runs of True."""
    out, t, n = [], 0, mask.shape[0]
    while t < n:
        if mask[t]:
            end = t
            while end + 1 < n and mask[end + 1]:
                end += 1
            out.append((t, end))
            t = end + 1
        else:
            t += 1
    return out


class Forced(torch.nn.Module):
    """The encoder, with the posterior's type forced at given edge-steps (type -> [B, E, T-1] bool)."""

    def __init__(self, encoder: torch.nn.Module, force: dict[int, torch.Tensor], k: int) -> None:
        super().__init__()
        self.encoder, self.force, self.k = encoder, force, k

    def forward(self, x, mask=None):
        out = self.encoder(x, mask)
        logits = out.posterior_logits.clone()
        for kind, where in self.force.items():
            logits[where] = F.one_hot(torch.tensor(kind), self.k).float() * 40.0 - 20.0
        out.posterior_logits = logits
        return out


def objective(net, batch, cut, force, draws=4) -> dict[str, float]:
    """The terms (batch means) of a given cut with forced types, averaged over draws of the edge types."""
    encoder, total = net.encoder, {}
    net.encoder = Forced(encoder, force, net.num_types)
    try:
        for draw in range(draws):
            torch.manual_seed(draw)
            with torch.no_grad():
                out = net.infer(batch, hard=True, cut=cut)
                terms = {**{k: v.mean() for k, v in out.terms.items()}, "nelbo": net.loss(out)["nelbo"]}
            for key, value in terms.items():
                total[key] = total.get(key, 0.0) + float(value) / draws
    finally:
        net.encoder = encoder
    return total


def main() -> None:
    args, model, net, batch = clips_from_command_line(__doc__.splitlines()[0], "synth/dider")
    truth = batch["edges"].transpose(1, 2) > 0  # [B, E, T-1]
    torch.manual_seed(0)
    with torch.no_grad():
        own = net.infer(batch, hard=True)
    held = own.posterior_types() > 0
    gate = own.seg.weight > 0.5  # the own cut's segment starts
    b_, e_, t_ = held.shape
    observed = net.capabilities.observed  # the burn-in's end: a fixed boundary
    lead_steps = tail_steps = spurious_steps = 0
    leads, tails, starts = [], [], torch.zeros(t_, dtype=torch.long)
    trimmed_gate, force_int, force_none = gate.clone(), torch.zeros_like(gate), torch.zeros_like(gate)
    for b in range(b_):
        for e in range(e_):
            for first, last in runs(held[b, e]):
                starts[first] += 1
                inside = truth[b, e, first:last + 1].nonzero().squeeze(-1)
                if inside.numel() == 0:
                    spurious_steps += last - first + 1
                    continue
                onset, end = first + int(inside[0]), first + int(inside[-1])
                lead_steps, tail_steps = lead_steps + onset - first, tail_steps + last - end
                leads.append(onset - first)
                tails.append(last - end)
                if onset > max(first, observed):  # the trimmed cut: start at the onset, none before it
                    for free in (0, observed):
                        if first <= free < onset:
                            force_none[b, e, free] = True
                    if first > observed:
                        force_none[b, e, first] = True
                    trimmed_gate[b, e, onset] = force_int[b, e, onset] = True
    lead, tail = torch.tensor(leads, dtype=torch.float), torch.tensor(tails, dtype=torch.float)
    q = torch.tensor([0.1, 0.25, 0.5, 0.75, 0.9])
    own_terms = objective(net, batch, gate, {})
    trimmed = objective(net, batch, trimmed_gate, {1: force_int, 0: force_none})
    weights = {k: t.weight for k, t in net.objective.terms.items()}
    record = {
        "command": "python " + " ".join(sys.argv), "clips": batch["states"].shape[0],
        "over_held_steps": {"lead": lead_steps, "tail": tail_steps, "spurious": spurious_steps},
        "held_runs": int(sum(starts)), "true_runs": int((truth & ~F.pad(truth[..., :-1], (1, 0))).sum()),
        "held_run_starts_by_step": starts.tolist(),
        "true_run_starts_by_step": (truth & ~F.pad(truth[..., :-1], (1, 0))).sum((0, 1)).tolist(),
        "lead_quantiles_10_25_50_75_90": lead.quantile(q).tolist(), "lead_mean": float(lead.mean()),
        "tail_quantiles_10_25_50_75_90": tail.quantile(q).tolist(), "tail_mean": float(tail.mean()),
        "runs_trimmed": int(force_int.sum()),
        "objective": {"own": own_terms, "trimmed": trimmed, "weights": weights,
                      "trimmed_minus_own_weighted": {k: (trimmed[k] - own_terms[k]) * weights.get(k, 1.0)
                                                     for k in own_terms}},
    }
    with open(args.out, "w") as f:
        json.dump(record, f, indent=1)
    print(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
