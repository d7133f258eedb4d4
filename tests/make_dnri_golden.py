"""Record golden outputs of the public DNRI code for ``tests/test_dnri_golden.py`` (a developer tool, not a test).

    .venv/bin/python tests/make_dnri_golden.py --reference PATH/TO/cvpr_dNRI

For each variant it builds the reference DNRI model (cgraber/cvpr_dNRI, MIT; imported from the checkout at
run time, nothing of it is copied here) at small sizes, randomises its biases and batch-norm statistics,
copies its weights into our module layout (``reference_to_ours``), feeds both the same fixed inputs and writes
``tests/golden/dnri/<variant>.pt``: the overrides of our model, our state_dict after the copy, the inputs
and the reference's outputs. It refuses to write if our model disagrees beyond the test's tolerances.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from dider.graph import edge_index  # noqa: E402
from test_dnri_golden import GOLDEN, TOLERANCE, VARIANTS, build_model, max_differences, our_outputs  # noqa: E402

REFERENCE_COMMIT = "ab7125c"  # the snapshot of cgraber/cvpr_dNRI the golden files were made from

# Small sizes keep the files well under 1 MB; the structure (3-layer heads, skip_first) is DNRI's.
B, T, N, D = 2, 12, 3, 4
BURN_IN, NUM_PRED = 6, 6  # the roll-out reads x_0..x_5 and predicts x_6..x_11
ENC_HIDDEN, RNN_HIDDEN, HEAD_HIDDEN, DEC_HIDDEN = 32, 16, 16, 32
NO_EDGE_PRIOR = 0.9  # DNRI synth's --add_uniform_prior --no_edge_prior 0.9 (ours: model/net/objective=dnri)
# Smallest allowed gap between the top two logits of any argmax edge decision: ~500x the logit differences
# measured between the implementations (~2e-7), so that the exact edge comparison cannot flip.
MIN_MARGIN = 1e-4
VARIANT_SETTINGS = {  # variant -> (our decoder config, reference decoder_type, edge types)
    "markov": ("markov", "ref_mlp", 2),
    "recurrent": ("recurrent", "recurrent", 2),
    "recurrent_k4": ("recurrent", "recurrent", 4),
}


def our_overrides(decoder: str, num_types: int) -> list[str]:
    """Hydra overrides of our model matching the reference built by ``reference_params``."""
    return [
        "model=dnri", f"model/net/decoder={decoder}", f"model.num_edges={num_types}",
        f"model.net.encoder.hidden={ENC_HIDDEN}", f"model.net.encoder.rnn_hidden={RNN_HIDDEN}",
        f"model.net.encoder.head_hidden={HEAD_HIDDEN}", f"model.net.prior.hidden={HEAD_HIDDEN}",
        f"model.net.decoder.hidden={DEC_HIDDEN}", "model.net.rollout_edges=argmax",
        "model/net/objective=dnri", f"model.net.objective.sparsity.no_edge_prob={NO_EDGE_PRIOR}",
        "model.net.objective.nll.variance=5e-5",
    ]  # fmt: skip


def reference_params(decoder_type: str, num_types: int) -> dict[str, object]:
    """The reference's ``params`` dict: DNRI's synth flags (run_synth.sh) at small sizes, on the CPU."""
    return {
        "num_vars": N, "input_size": D, "num_edge_types": num_types, "skip_first": True, "gpu": False,
        "encoder_hidden": ENC_HIDDEN, "encoder_rnn_hidden": RNN_HIDDEN, "encoder_rnn_type": "lstm",
        "encoder_mlp_num_layers": 3, "encoder_mlp_hidden": HEAD_HIDDEN, "encoder_dropout": 0.0,
        "prior_num_layers": 3, "prior_hidden_size": HEAD_HIDDEN,
        "decoder_type": decoder_type, "decoder_hidden": DEC_HIDDEN, "decoder_dropout": 0.0,
        "gumbel_temp": 0.5, "train_hard_sample": False, "teacher_forcing_steps": -1, "val_teacher_forcing_steps": -1,
        "normalize_kl": True, "normalize_nll": True, "nll_loss_type": "gaussian", "prior_variance": 5e-5,
        "kl_coef": 1.0, "add_uniform_prior": True, "no_edge_prior": NO_EDGE_PRIOR,
    }  # fmt: skip


@torch.no_grad()
def randomize_(ref: nn.Module, gen: torch.Generator) -> None:
    """Give every bias and batch-norm parameter/statistic its own random value. DNRI's init sets all encoder
    biases to 0.1 and the batch norms to the identity, which would hide a swapped bias or a batch norm
    mapped onto the wrong layer."""
    for name, p in ref.named_parameters():
        if not p.requires_grad:  # edge2node_mat: fixed incidence matrices
            continue
        leaf = name.rsplit(".", 1)[-1]
        if ".bn." in name and leaf == "weight":
            p.copy_(torch.rand(p.shape, generator=gen) + 0.5)
        elif name.startswith("decoder.") and leaf == "bias":
            # Mostly positive: the decoders' ReLU layers see small inputs, and with biases in +-0.3 a third of
            # their units never fired on the fixed inputs, leaving their weights untested.
            p.copy_(torch.rand(p.shape, generator=gen) * 0.4 - 0.05)
        elif leaf.startswith("bias"):  # Linear bias, LSTM bias_ih_l0 / bias_hh_l0, batch-norm bias
            p.copy_(torch.rand(p.shape, generator=gen) * 0.6 - 0.3)
    for name, buf in ref.named_buffers():
        if name.endswith("running_mean"):
            buf.copy_(torch.randn(buf.shape, generator=gen) * 0.2)
        elif name.endswith("running_var"):
            buf.copy_(torch.rand(buf.shape, generator=gen) * 1.5 + 0.5)


def reference_to_ours(ref_sd: dict[str, torch.Tensor], decoder: str, num_types: int) -> tuple[dict, set[str]]:
    """Our state_dict from the reference's, and the reference keys it used.

    Layout differences handled here:
    - Encoder GNN: DNRI's ``mlpX.model.0`` Linear on [send, recv(, skip)] is our PairLinear ``*_in``, whose weight
      columns are in the same order (first block applied to the sender): copied as is.
    - Posterior head: DNRI reads [h_fwd, h_rev], we read [h_rev, h_fwd]: the first layer's column halves swap.
    - Decoder messages: DNRI's ``msg_fc1[k]`` reads [recv, send], our PairLinear [send, recv]: column halves
      swap; the message types k >= 1 are stacked along the output rows in type order. ``msg_fc2[k]`` ([out, in])
      becomes slice k-1 of our TypedLinear weight [K-1, in, out]: transposed. Type 0's message MLP (skip_first)
      is never used by DNRI and has no counterpart here.
    - Recurrent decoder gates: DNRI's input_r/i/n and hidden_r/i/h Linears are our ``input_gates`` and
      ``message_gates`` with the three blocks stacked along the rows in the order r, i, n (our chunk order).
    """
    used: set[str] = set()

    def take(key: str) -> torch.Tensor:
        used.add(key)
        return ref_sd[key].clone()

    def swap_halves(w: torch.Tensor) -> torch.Tensor:
        half = w.shape[1] // 2
        return torch.cat([w[:, half:], w[:, :half]], dim=1)

    ours: dict[str, torch.Tensor] = {}
    # --- encoder: the four NRI MLPs (Linear, ELU, Dropout, Linear, ELU, BatchNorm) ----------------------
    for ref_mlp, first, rest in (("mlp1", "node1.fc1", "node1"), ("mlp2", "edge1_in", "edge1"),
                                 ("mlp3", "node2.fc1", "node2"), ("mlp4", "edge2_in", "edge2")):  # fmt: skip
        src, dst = f"encoder.{ref_mlp}", "encoder.embed"
        ours[f"{dst}.{first}.weight"] = take(f"{src}.model.0.weight")
        ours[f"{dst}.{first}.bias"] = take(f"{src}.model.0.bias")
        ours[f"{dst}.{rest}.fc2.weight"] = take(f"{src}.model.3.weight")  # model.1/.2 are ELU/Dropout
        ours[f"{dst}.{rest}.fc2.bias"] = take(f"{src}.model.3.bias")
        for leaf in ("weight", "bias", "running_mean", "running_var", "num_batches_tracked"):
            ours[f"{dst}.{rest}.bn.{leaf}"] = take(f"{src}.bn.{leaf}")
    # --- encoder LSTMs: same nn.LSTM parameters, same gate order ---------------------------------------
    for rnn in ("forward_rnn", "reverse_rnn"):
        for leaf in ("weight_ih_l0", "weight_hh_l0", "bias_ih_l0", "bias_hh_l0"):
            ours[f"encoder.{rnn}.{leaf}"] = take(f"encoder.{rnn}.{leaf}")
    # --- heads: Sequential(Linear, ELU, Linear, ELU, Linear) on both sides ------------------------------
    for i in (0, 2, 4):
        for leaf in ("weight", "bias"):
            ours[f"prior.net.{i}.{leaf}"] = take(f"encoder.prior_fc_out.{i}.{leaf}")
            w = take(f"encoder.encoder_fc_out.{i}.{leaf}")
            ours[f"encoder.posterior_head.{i}.{leaf}"] = swap_halves(w) if (i, leaf) == (0, "weight") else w
    # --- decoder messages (types 1..K-1) ---------------------------------------------------------------
    types = range(1, num_types)
    ours["decoder.messages.fc1.weight"] = torch.cat([swap_halves(take(f"decoder.msg_fc1.{k}.weight")) for k in types])
    ours["decoder.messages.fc1.bias"] = torch.cat([take(f"decoder.msg_fc1.{k}.bias") for k in types])
    ours["decoder.messages.fc2.weight"] = torch.stack([take(f"decoder.msg_fc2.{k}.weight").T for k in types])
    ours["decoder.messages.fc2.bias"] = torch.stack([take(f"decoder.msg_fc2.{k}.bias") for k in types])
    # --- decoder output MLP: out_fc1/2/3 -> Sequential indices 0/3/6 (ReLU, Dropout in between) ----------
    for ref_fc, i in (("out_fc1", 0), ("out_fc2", 3), ("out_fc3", 6)):
        ours[f"decoder.out.{i}.weight"] = take(f"decoder.{ref_fc}.weight")
        ours[f"decoder.out.{i}.bias"] = take(f"decoder.{ref_fc}.bias")
    if decoder == "recurrent":  # GRU-style gates
        gates = ("r", "i", "n")
        ours["decoder.input_gates.weight"] = torch.cat([take(f"decoder.input_{g}.weight") for g in gates])
        ours["decoder.input_gates.bias"] = torch.cat([take(f"decoder.input_{g}.bias") for g in gates])
        # DNRI names the candidate's message gate hidden_h; it pairs with input_n.
        ours["decoder.message_gates.weight"] = torch.cat([take(f"decoder.hidden_{g}.weight") for g in ("r", "i", "h")])
    return ours, used


@contextlib.contextmanager
def argmax_edges(model_utils: object) -> Iterator[list[float]]:
    """Make the reference's edge sampler return the argmax one-hot, so its loss and roll-out are deterministic
    (DNRI samples hard Gumbel-softmax edges at evaluation; ours: ``model.net.rollout_edges=argmax``). Yields a
    list that collects, per call, the smallest gap between the two largest logits: an argmax decided by less
    than the float error between the two implementations could flip on another machine."""
    margins: list[float] = []

    def one_hot_argmax(logits: torch.Tensor, tau: float = 1.0, hard: bool = False, eps: float = 1e-10) -> torch.Tensor:
        top2 = logits.topk(2, dim=-1).values
        margins.append((top2[..., 0] - top2[..., 1]).min().item())
        return F.one_hot(logits.argmax(-1), logits.shape[-1]).to(logits.dtype)

    original: Callable = model_utils.gumbel_softmax
    model_utils.gumbel_softmax = one_hot_argmax
    try:
        yield margins
    finally:
        model_utils.gumbel_softmax = original


@torch.no_grad()
def balance_logits_(ref: nn.Module, x: torch.Tensor) -> None:
    """Shift the last bias of the prior and posterior heads so that, on ``x``, every edge type's logit has
    mean 0. With random weights the random biases otherwise make one type win almost everywhere, and the
    messages of the other types would go unchecked in the roll-out and in the posterior-driven NLL. (Not
    scaled: a larger logit spread would scale up the float differences between the implementations alike.)"""
    prior_logits, posterior_logits, _ = ref.encoder(x[:, :-1])
    for layer, logits in (
        (ref.encoder.prior_fc_out[-1], prior_logits),
        (ref.encoder.encoder_fc_out[-1], posterior_logits),
    ):
        layer.bias.sub_(logits.mean(dim=(0, 1, 2)))


def make_inputs(gen: torch.Generator, num_types: int) -> dict[str, torch.Tensor | int]:
    """Smooth trajectories [x, y, vx, vy] on DNRI's normalised scale, and random one-hot edges."""
    vel = 0.05 * torch.randn(B, T, N, 2, generator=gen) + 0.1 * torch.randn(B, 1, N, 2, generator=gen)
    loc = torch.rand(B, 1, N, 2, generator=gen) * 2 - 1 + vel.cumsum(1)
    z = F.one_hot(torch.randint(num_types, (B, T - 1, N * (N - 1)), generator=gen), num_types).float()
    return {"x": torch.cat([loc, vel], dim=-1), "z": z, "burn_in": BURN_IN, "num_pred": NUM_PRED}


@torch.no_grad()
def reference_outputs(ref: nn.Module, model_utils: object, inputs: dict) -> tuple[dict[str, torch.Tensor], float]:
    """The reference's outputs through its own entry points, in its layouts (see the test's docstring), and
    the smallest top-2 logit gap of its argmax edge decisions."""
    x, z = inputs["x"], inputs["z"]
    out: dict[str, torch.Tensor] = {}
    prior_logits, posterior_logits, _ = ref.encoder(x[:, :-1])  # DNRI's encoder never sees the last frame
    out["prior_logits"], out["posterior_logits"] = prior_logits, posterior_logits
    hidden, preds = ref.decoder.get_initial_hidden(x), []
    for t in range(T - 1):  # one decoder call per step, ground truth in, as calculate_loss does
        pred, hidden = ref.decoder(x[:, t], hidden, z[:, t])
        preds.append(pred)
    out["decoder_pred"] = torch.stack(preds, dim=1)
    with argmax_edges(model_utils) as margins:
        # calculate_loss(is_train=False): teacher-forced, hard posterior edges (here argmax), normalised NLL
        # and KL, the KL mixed 0.5/0.5 with KL(mean_e q || [0.9, 0.1]) (add_uniform_prior).
        _, out["nll"], out["kl"] = ref.calculate_loss(x)
        preds, edges = ref.predict_future(x[:, :BURN_IN], NUM_PRED, return_edges=True, return_everything=True)
    # return_everything: the BURN_IN-1 burn-in predictions come first, then the NUM_PRED forecasts; the edges
    # cover every transition.
    out["rollout_pred"] = preds[:, BURN_IN - 1 :]
    out["rollout_types"] = edges.argmax(-1)
    if min(margins) < MIN_MARGIN:
        raise RuntimeError(f"an argmax edge is decided by {min(margins):.2g} < {MIN_MARGIN}: try another seed")
    return out, min(margins)


@torch.no_grad()
def realigned_posterior(ours: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """Our posterior head read on DNRI's windows, [B, T-1, E, K]: a check of the mapping of the reverse LSTM and
    the posterior head, which the test cannot pin (it does not compare the posterior, see its docstring).

    For transition t DNRI's reverse LSTM has read x_t..x_{T-2}, ours x_{t+1}..x_{T-1}. Prepending one frame
    shifts our reverse window onto DNRI's; the forward half is read from the unshifted clip."""
    shifted = torch.cat([x[:, :1], x[:, :-1]], dim=1)
    h_rev, h_fwd = ours.encoder(shifted).h_rev, ours.encoder(x).h_fwd
    return ours.encoder.posterior_head(torch.cat([h_rev, h_fwd], dim=-1)).transpose(1, 2)


def check_edge_order(ref: nn.Module) -> None:
    """Both sides enumerate directed edges sender-major (row-major off-diagonal), so no permutation is needed."""
    send, recv = edge_index(N)
    for module in (ref.encoder, ref.decoder):
        assert (torch.as_tensor(module.send_edges) == send).all() and (torch.as_tensor(module.recv_edges) == recv).all()


def make_variant(variant: str, reference_dnri: type, model_utils: object, seed: int) -> dict:
    """Build both models for ``variant``, copy the weights, run both; -> the golden dict."""
    decoder, decoder_type, num_types = VARIANT_SETTINGS[variant]
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)  # the reference initialises from the global RNG
    ref = reference_dnri(reference_params(decoder_type, num_types))
    randomize_(ref, gen)
    ref.eval()
    check_edge_order(ref)
    inputs = make_inputs(gen, num_types)
    balance_logits_(ref, inputs["x"])

    overrides = our_overrides(decoder, num_types)
    ours = build_model(overrides)
    mapped, used = reference_to_ours(ref.state_dict(), decoder, num_types)
    ours.load_state_dict(mapped)  # strict: every one of our parameters and buffers is mapped
    unused = set(ref.state_dict()) - used
    expected_unused = {"encoder.edge2node_mat", "decoder.edge2node_mat"} | {
        f"decoder.msg_fc{i}.0.{leaf}" for i in (1, 2) for leaf in ("weight", "bias")
    }  # skip_first: type 0 unused
    assert unused == expected_unused, f"unmapped reference keys: {sorted(unused - expected_unused)}"

    ref_out, margin = reference_outputs(ref, model_utils, inputs)
    diffs = max_differences(our_outputs(ours, inputs, ref_out["posterior_logits"]), ref_out)
    posterior_diff = (realigned_posterior(ours, inputs["x"]) - ref_out["posterior_logits"]).abs().max().item()
    return {
        "overrides": overrides,
        "state_dict": {k: v.detach().clone() for k, v in ours.state_dict().items()},
        "inputs": inputs,
        "reference": {k: v.detach().clone() for k, v in ref_out.items()},  # clone: no views of larger storages
        "measured": diffs,  # max differences at generation time, for the record
        "meta": {
            "reference": f"cgraber/cvpr_dNRI@{REFERENCE_COMMIT}",
            "torch": str(torch.__version__),
            "seed": seed,
            "min_argmax_margin": margin,
            "posterior_realigned_max_diff": posterior_diff,
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reference", type=Path, required=True, help="checkout of cgraber/cvpr_dNRI")
    parser.add_argument("--out", type=Path, default=GOLDEN)
    args = parser.parse_args()
    sys.path.insert(0, str(args.reference.resolve()))
    from dnri.models import model_utils  # the reference, imported by path
    from dnri.models.dnri import DNRI

    torch.set_num_threads(1)
    results = {}
    with contextlib.redirect_stdout(sys.stderr):  # the reference prints on construction
        for seed, variant in enumerate(VARIANTS):
            results[variant] = make_variant(variant, DNRI, model_utils, seed)
    failed = False
    for variant, golden in results.items():
        for key, diff in golden["measured"].items():
            ok = diff <= TOLERANCE[key]
            failed |= not ok
            print(f"{variant:13s} {key:14s} max diff {diff:.3g} (tolerance {TOLERANCE[key]:g}){'' if ok else '  FAIL'}")
        meta = golden["meta"]
        print(f"{variant:13s} smallest top-2 logit gap of an argmax edge: {meta['min_argmax_margin']:.3g}")
        ok = meta["posterior_realigned_max_diff"] <= TOLERANCE["prior_logits"]  # same scale as the prior's logits
        failed |= not ok
        print(
            f"{variant:13s} posterior, reverse window realigned (not in the test): max diff "
            f"{meta['posterior_realigned_max_diff']:.3g}{'' if ok else '  FAIL'}"
        )
    if failed:
        sys.exit("our model disagrees with the reference beyond the test's tolerances: golden files not written")
    args.out.mkdir(parents=True, exist_ok=True)
    for variant, golden in results.items():
        path = args.out / f"{variant}.pt"
        torch.save(golden, path)
        print(f"wrote {path} ({path.stat().st_size / 1024:.1f} KiB)")


if __name__ == "__main__":
    main()
