"""The objective's terms (dider.models.objective): hand values, the weighted sum and its schedules, the settings
each term checks."""

import math

import pytest
import torch

from dider.models.objective import EdgeKL, Objective, PriorFit, Sparsity
from dider.models.plugins import Progress
from dider.training.preflight import validate_config
from dider.validation import ConfigError
from helpers import NO_SPARSITY
from helpers.models import build, clip


def test_each_model_reads_its_objective_from_the_config_group(make_cfg):
    terms = {m: list(build(make_cfg, f"model={m}").objective.terms) for m in ("dnri", "dider", "dider_paper", "nri")}
    assert terms == {"dnri": ["nll", "kl_edge", "kl_duration", "sparsity"],
                     "dider": ["nll", "kl_edge", "kl_duration", "sparsity", "prior_fit", "boundary_fit",
                               "indifference"],
                     "dider_paper": ["nll", "kl_edge", "kl_duration", "sparsity"],
                     "nri": ["nll", "kl_edge", "kl_duration"]}
    dider = build(make_cfg, "model=dider").objective.terms
    assert (dider["kl_edge"].weight, dider["sparsity"].weight, dider["sparsity"].form) == (0.5, 0.5, "per_edge")


def test_loss_is_the_weighted_sum_with_warm_up_and_capacities(make_cfg):
    """loss = NLL + sum_i weight_i w |term_i - C_i|: by hand at a quarter of training, with the KL warm-up over
    the first 30% (w = 25/30) and the edge KL's capacity 0.2 ramped over half of training (C = 0.2 * 25/50)."""
    net = build(make_cfg, "model=dider", "model/net/objective=dider", "model.net.objective.kl_warmup=0.3",
                "model.net.objective.kl_edge.capacity=0.2", "model.net.objective.prior_fit.weight=2")
    out = net.infer(clip(), hard=True)
    progress = Progress(25, total=100)
    terms = net.loss(out, progress)
    m = {k: v.mean() for k, v in out.terms.items()}
    w, c = 25 / 30, 0.2 * 25 / 50
    expected = (m["nll"] + 0.5 * w * (m["kl_edge"] - c).abs() + 1.0 * w * m["kl_duration"].abs()
                + 0.5 * w * m["sparsity"] + 2 * w * m["prior_fit"] + 1.0 * w * m["boundary_fit"])
    assert torch.allclose(terms["loss"], expected)
    assert net.schedule(progress)["capacity/kl_edge"] == pytest.approx(c)
    # nelbo: no schedule, no capacity, and not the prior fit (outside the ELBO)
    nelbo = m["nll"] + 0.5 * m["kl_edge"] + m["kl_duration"] + 0.5 * m["sparsity"]
    assert torch.allclose(terms["nelbo"], nelbo) and all(m[k] > 0 for k in ("kl_edge", "sparsity", "prior_fit"))
    assert net.loss(out, Progress(0, total=100))["loss"] == m["nll"]  # w = 0 at the first step: the NLL alone


def test_edge_kl_per_step_counts_each_segment_once_per_step(make_cfg):
    batch = clip()
    torch.manual_seed(2)
    once = build(make_cfg, "model=dider_paper", *NO_SPARSITY).eval()
    per_step = build(make_cfg, "model=dider_paper", *NO_SPARSITY, "model.net.objective.kl_edge.count=per_step").eval()
    per_step.load_state_dict(once.state_dict())
    with torch.no_grad():
        a, b = once.infer(batch, hard=True), per_step.infer(batch, hard=True)
    assert (a.seg.num_steps_per_slot > 1).any()  # some segment holds several steps: the two weightings differ there
    assert b.terms["kl_edge"].sum() > a.terms["kl_edge"].sum()
    dnri = build(make_cfg, "model=dnri", *NO_SPARSITY).eval()
    dnri_steps = build(make_cfg, "model=dnri", *NO_SPARSITY, "model.net.objective.kl_edge.count=per_step").eval()
    dnri_steps.load_state_dict(dnri.state_dict())
    with torch.no_grad():  # one-step segments: both are DNRI's mean over (step, edge)
        a, b = dnri.infer(batch, hard=True), dnri_steps.infer(batch, hard=True)
    assert torch.equal(a.terms["kl_edge"], b.terms["kl_edge"])


def test_prior_fit_trains_the_prior_at_every_step_and_leaves_the_posterior(make_cfg):
    batch = clip()
    off = build(make_cfg, "model=dider_paper").train()
    on = build(make_cfg, "model=dider_paper", "model.net.objective.prior_fit={_target_: "
               "dider.models.objective.PriorFit, weight: 0.5}").train()
    on.load_state_dict(off.state_dict())
    torch.manual_seed(3)
    a = off.loss(off.infer(batch, hard=True))
    torch.manual_seed(3)
    b = on.loss(on.infer(batch, hard=True))
    # outside the ELBO: in the loss at its weight; the selection objective ignores it
    assert "prior_fit" not in a and b["prior_fit"] > 0
    assert torch.allclose(b["loss"], a["loss"] + 0.5 * b["prior_fit"]) and torch.equal(a["nelbo"], b["nelbo"])
    b["prior_fit"].backward()
    assert sum(p.grad.abs().sum() for p in on.prior.parameters()) > 0
    posterior_only = [*on.encoder.reverse_rnn.parameters(), *on.encoder.posterior_head.parameters()]
    assert all(p.grad is None or not p.grad.any() for p in posterior_only)
    # with one-step segments the held posterior is the per-step one: the fit is DNRI's edge KL
    dnri = build(make_cfg, "model=dnri", *NO_SPARSITY).eval()
    with torch.no_grad():
        out = dnri.infer(batch, hard=True)
    fit = PriorFit()(out, batch)
    assert torch.allclose(fit, out.terms["kl_edge"], rtol=1e-5, atol=1e-7)


def _one_hot_steps(marked: list[int], edges: int = 6) -> torch.Tensor:
    """Confident posteriors at one step of one clip: type 1 on the ``marked`` edges, else type 0. -> [1, E, 1, 2]"""
    probs = torch.zeros(1, edges, 1, 2, dtype=torch.float64)
    probs[0, :, 0, 0] = 1.0
    probs[0, marked, 0] = torch.tensor([0.0, 1.0], dtype=torch.float64)
    return probs


@pytest.mark.parametrize("form", ["mean_edges", "per_edge"])
def test_sparsity_forms_hand_values(form):
    """Against [0.9, 0.1], at a step with 6 present edges. mean_edges: KL of the edges' mean q, so no edge
    marked costs log(1/0.9) and one marked edge (mean [5/6, 1/6], nearer the 10% budget) costs less: the term
    pays for marking an edge that does nothing. per_edge: the mean of each edge's KL, log(1/0.9) per unmarked
    and log(1/0.1) per marked edge: every mark costs more."""
    term = Sparsity(no_edge_prob=0.9, form=form).double()
    present = torch.ones(1, 6, 1, dtype=torch.bool)
    none, one = (term.of(_one_hot_steps(m), present).item() for m in ([], [2]))
    if form == "mean_edges":
        expected_one = 5 / 6 * math.log(5 / 6 / 0.9) + 1 / 6 * math.log(1 / 6 / 0.1)
        assert none == pytest.approx(math.log(1 / 0.9)) and one == pytest.approx(expected_one)
        assert one < none
    else:
        expected_one = (5 * math.log(1 / 0.9) + math.log(1 / 0.1)) / 6
        assert none == pytest.approx(math.log(1 / 0.9)) and one == pytest.approx(expected_one)
        assert one > none
    # absent edges are left out of either form: two edges absent, the marked one among them
    present[0, [2, 3]] = False
    assert term.of(_one_hot_steps([2]), present).item() == pytest.approx(math.log(1 / 0.9))


def test_terms_check_their_settings_at_build_and_in_the_preflight(make_cfg, tmp_path):
    with pytest.raises(ConfigError, match=r"EdgeKL: capacity=-0.5: must be >= 0"):
        EdgeKL(capacity=-0.5)
    with pytest.raises(ConfigError, match=r"Sparsity: form='per_step': expected one of \['mean_edges', 'per_edge'\]"):
        Sparsity(form="per_step")
    with pytest.raises(ConfigError, match=r"Objective: kl_warmup=1.5"):
        Objective(kl_warmup=1.5, nll=None)
    with pytest.raises(ValueError, match="needs an `nll` term"):
        Objective()
    cfg = make_cfg(["model.net.objective.kl_edge.capacity=-0.5", "model.net.objective.nll.variance=0",
                    "model.net.objective.sparsity.form=per_step", "model.net.objective.kl_warmup=2"],
                   out=tmp_path / "run")
    with pytest.raises(ConfigError) as error:
        validate_config(cfg)
    message = str(error.value)
    for expected in ("model.net.objective.kl_edge.capacity=-0.5: must be >= 0",
                     "model.net.objective.nll.variance=0: must be > 0 or 'fit'",
                     "model.net.objective.sparsity.form='per_step'", "model.net.objective.kl_warmup=2"):
        assert expected in message
