"""The edge evidence (MarkovDecoder.edge_evidence) against one decoder pass per edge and type, and the
indifference term (dider.models.objective.Indifference) by hand."""

from types import SimpleNamespace

import pytest
import torch

from dider.graph import edge_index
from dider.models.decoders import MarkovDecoder, RecurrentDecoder, evidence_problem
from dider.models.likelihood import GaussianNLL
from dider.models.losses import gaussian_nll_each
from dider.models.objective import Indifference, Objective
from dider.models.plugins import Progress
from helpers.models import build, clip


def _nll(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return gaussian_nll_each(pred, target, 1e-2)


@pytest.mark.parametrize("decoder", [MarkovDecoder, RecurrentDecoder])
@pytest.mark.parametrize("num_types", [2, 3])
def test_edge_evidence_is_the_receivers_nll_with_the_edge_at_none_minus_at_its_best_type(decoder, num_types):
    torch.manual_seed(0)
    b, t, n, d = 2, 3, 4, 4
    dec = decoder(num_types, input_dim=d, hidden=8).eval()
    x, target = torch.randn(b, t, n, d), torch.randn(b, t, n, d)
    z = torch.softmax(torch.randn(b, t, n * (n - 1), num_types), -1)
    mask = torch.rand(b, t, n) > 0.2
    got = dec.edge_evidence(x, z, target, mask, _nll)  # [B, T, E]
    send, recv = edge_index(n)
    expected = torch.zeros_like(got)
    for s in range(t):  # one full decoder pass per step, edge and type, the edge swapped at that step only
        for e in range(n * (n - 1)):
            costs = []
            for k in range(num_types):
                zk = z.clone()
                zk[:, s, e] = torch.nn.functional.one_hot(torch.tensor(k), num_types).float()
                pred = dec(x, zk, mask)
                costs.append(_nll(pred[:, s, recv[e]], target[:, s, recv[e]]))
            best = torch.stack(costs[1:], -1).amin(-1)
            expected[:, s, e] = (costs[0] - best) * (mask[:, s, send[e]] & mask[:, s, recv[e]])
    # each evidence is a difference of NLLs in the hundreds (variance 1e-2): fp32 keeps ~1e-5 of them, and CPUs'
    # kernels differ in the last bits
    assert torch.allclose(got, expected, atol=2e-4)
    assert (got != 0).any()


def test_edge_evidence_needs_a_silent_type_0():
    dec = MarkovDecoder(2, input_dim=4, hidden=8, skip_first=False)
    with pytest.raises(ValueError, match="skip_first"):
        dec.edge_evidence(torch.zeros(1, 1, 2, 4), torch.zeros(1, 1, 2, 2), torch.zeros(1, 1, 2, 4), None, _nll)


def test_indifference_charges_marked_edge_steps_where_the_evidence_is_below_the_threshold(make_cfg):
    net = build(make_cfg, "model=dider", "model.net.objective.indifference.threshold=0.5",
                "model.net.objective.indifference.weighting=backed_share")
    term = net.objective.terms["indifference"]  # model=dider's objective
    assert (term.weight, term.threshold, term.after, term.from_step) == (2.0, 0.5, 0.25, 1000)
    out = net.infer(clip(), hard=True)
    assert out.evidence is not None and out.evidence.shape == out.present.shape
    indifferent = (out.evidence < 0.5) & out.present
    marked = (1 - out.probs[..., 0]) * out.present
    backed = (marked * ~indifferent).sum() / marked.sum()  # every receiver present: every step scored
    assert 0 < backed < 1
    by_hand = (marked * indifferent).flatten(1).sum(1) / out.present.flatten(1).sum(1)
    assert torch.allclose(out.terms["indifference"], by_hand * backed)
    assert torch.allclose(out.terms["indifference/backed"], backed.expand_as(by_hand))
    # the evidence is computed without a gradient; the term's gradient reaches the posterior through probs
    out.terms["indifference"].sum().backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in net.encoder.parameters())
    assert "indifference" not in build(make_cfg, "model=dider", "model/net/objective=dider").objective.terms


def test_the_backed_share_by_hand():
    # one edge, four steps: held interaction mass 0.5, 1, 0, 0.25; evidence 2, 0.5, 3, and unscored (receiver gone)
    out = SimpleNamespace(probs=torch.tensor([[[[0.5, 0.5], [0.0, 1.0], [1.0, 0.0], [0.75, 0.25]]]]),
                          evidence=torch.tensor([[[2.0, 0.5, 3.0, float("inf")]]]), present=torch.ones(1, 1, 4).bool(),
                          pred=torch.zeros(1, 3, 2, 4))
    share, fixed = Indifference(threshold=1.0), Indifference(threshold=1.0, weighting="fixed")
    assert torch.allclose(share.stats(out)["backed"], torch.tensor([0.5 / 1.5]))  # of the scored mass 1.5, 0.5 passes
    assert torch.allclose(fixed(out, {}), torch.tensor([1.0 / 4]))  # step 1's mass over 4 present edge-steps
    assert torch.allclose(share(out, {}), torch.tensor([1.0 / 4 / 3]))
    out.evidence = torch.full((1, 1, 4), 0.5)  # nothing backed (a decoder that has learned nothing): the term is off
    assert share(out, {}).item() == 0.0 and fixed(out, {}).item() > 0
    out.probs = torch.tensor([[[[1.0, 0.0]] * 4]])  # nothing held: a share of 0, not NaN
    assert share.stats(out)["backed"].item() == 0.0


def test_indifference_is_off_for_the_first_part_of_training(make_cfg):
    net = build(make_cfg, "model=dider", "model/net/objective=dider_indifference",
                "model.net.objective.indifference.weight=1.0", "model.net.objective.indifference.after=0.3",
                "model.net.objective.indifference.from_step=0")
    out = net.infer(clip(), hard=True)
    assert out.terms["indifference"].sum() > 0
    early, late = net.loss(out, Progress(29, total=100)), net.loss(out, Progress(30, total=100))
    assert net.schedule(Progress(29, total=100))["on/indifference"] == 0.0
    # weight 1, KL warm: the loss differs by the term (to float32 rounding of a loss near 3e4)
    assert torch.allclose(late["loss"] - early["loss"], out.terms["indifference"].mean(), atol=1e-2)


def test_a_start_in_optimiser_steps_holds_at_any_length_of_training():
    term = Indifference(weighting="fixed", from_step=600)
    assert [term.start(Progress(0, total=n)) for n in (1000, 5000)] == [600, 600]
    assert term.start(Progress(0)) == 0  # the run's length unknown (a trained model): charged, as every schedule ends
    both = Indifference(weighting="fixed", after=0.25, from_step=600)  # the later of the two
    assert [both.start(Progress(0, total=n)) for n in (1000, 5000)] == [600, 1250]
    objective = Objective(nll=GaussianNLL(), indifference=term)
    assert [objective.schedule(Progress(s, total=5000))["on/indifference"] for s in (599, 600)] == [0.0, 1.0]
    with pytest.raises(ValueError, match="from_step.*integer"):
        Indifference(from_step=0.5)


@pytest.mark.parametrize("override, why", [("model.net.decoder.skip_first=false", "skip_first=true"),
                                           ("model.net.decoder.dropout=0.1", "dropout=0")])
@pytest.mark.parametrize("decoder", ["markov", "recurrent"])
def test_indifference_needs_a_decoder_that_gives_the_evidence(make_cfg, decoder, override, why):
    with pytest.raises(Exception, match=f"evidence.*{why}"):
        build(make_cfg, "model=dider", f"model/net/decoder={decoder}", override,
              "model/net/objective=dider_indifference")
    assert evidence_problem(torch.nn.Linear(1, 1)).endswith("does not give (model.net.decoder=markov and recurrent do)")


def test_the_evidence_is_computed_in_the_weights_dtype_at_least_float32():
    torch.manual_seed(0)
    dec = MarkovDecoder(2, input_dim=4, hidden=8).double()
    x, z = torch.randn(1, 2, 3, 4, dtype=torch.float64), torch.rand(1, 2, 6, 2, dtype=torch.float64)
    got = dec.edge_evidence(x, z, torch.randn(1, 2, 3, 4), None, _nll)  # weights in float64: no dtype clash
    assert got.dtype == torch.float64 and got.shape == (1, 2, 6)


def test_an_absent_receiver_is_never_indifferent(make_cfg):
    net = build(make_cfg, "model=dider", "model/net/objective=dider_indifference")
    batch = clip()
    batch["mask"] = batch["mask"].clone()
    batch["mask"][:, 10:, 0] = False  # agent 0 leaves after step 9
    out = net.infer(batch, hard=True)
    _, recv = edge_index(3)
    assert torch.isinf(out.evidence[:, recv == 0, 9:]).all() and torch.isfinite(out.evidence[:, recv != 0]).all()


def test_a_training_pass_before_the_start_skips_the_evidence(make_cfg):
    net = build(make_cfg, "model=dider", "model/net/objective=dider_indifference",
                "model.net.objective.indifference.after=0", "model.net.objective.indifference.from_step=5")
    before, after = Progress(4, total=100), Progress(5, total=100)
    assert not net.objective.reads_evidence(before) and net.objective.reads_evidence(after)
    assert net.objective.reads_evidence(Progress(4))  # validation (run length not asked): every term counts
    torch.manual_seed(0)
    skipped = net.infer(clip(), hard=True, progress=before)
    assert skipped.evidence is None and (skipped.terms["indifference"] == 0).all()
    assert (skipped.terms["indifference/backed"] == 0).all()
    torch.manual_seed(0)
    scored = net.infer(clip(), hard=True, progress=after)
    assert scored.evidence is not None and (scored.terms["indifference"] > 0).any()
    # the skipped term is not charged, so the loss is the same as with the evidence computed
    assert torch.equal(net.loss(skipped, before)["loss"], net.loss(scored, before)["loss"])


def test_validation_scores_the_term_before_its_start(make_cfg):
    """A validation (or test) pass asks the network at the step count alone, so the evidence is computed and the
    term counts in ``nelbo`` (what selects checkpoints) however early in training: only its charge waits."""
    from dider.training.module import RelationalVAEModule

    module = RelationalVAEModule.from_config(make_cfg(["model=dider"]).model)
    module.model.eval()
    with torch.no_grad():
        out = module._infer(clip(), hard=True)  # global_step 0, before the start (1000 steps)
    assert out.evidence is not None and (out.terms["indifference"] > 0).any()
    objective, early = module.model.objective, Progress(0, total=5000)
    without = dict(out.terms) | {"indifference": torch.zeros_like(out.terms["indifference"])}
    counted, charged = objective(out.terms, early), objective(without, early)
    # float32 rounding of a NELBO near 3e4
    assert torch.allclose(counted["nelbo"] - charged["nelbo"], 2.0 * out.terms["indifference"].mean(), atol=1e-2)
    assert torch.equal(counted["loss"], charged["loss"])  # not charged before its start
