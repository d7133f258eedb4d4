"""DIDER's segment machinery: invariants, reduction to DNRI, gradients, causality."""

import pytest
import torch

from dider.models.durations import LearnedDuration
from helpers.models import build, clip


@pytest.mark.parametrize("source", ["past", "future"])
@pytest.mark.parametrize("training", [True, False])
def test_segments_tile_the_clip(source, training):
    torch.manual_seed(0)
    dur = LearnedDuration(rnn_hidden=8, hidden=8, source=source).train(training)
    with torch.no_grad():  # spread the durations: some long, some short
        dur.head[-1].bias.copy_(torch.tensor([0.0, 1.0]))
        dur.head[-1].weight.mul_(20)
    t = 25
    h_fwd, h_rev = torch.randn(3, 6, t, 8), torch.randn(3, 6, t, 8)
    seg = dur.segment(h_fwd, h_rev, torch.zeros(3, t + 1, 3, 4))
    a = seg.assign.detach()
    assert a.shape[-1] <= t  # the slots stop once every edge's cover the clip
    assert torch.equal(a.sum(-1), torch.ones(3, 6, t))  # every step in exactly one slot (exact one-hot)
    assert set(a.unique().tolist()) <= {0.0, 1.0}
    slot = a.argmax(-1)
    assert (slot[..., 1:] - slot[..., :-1] >= 0).all() and (slot[..., 1:] - slot[..., :-1] <= 1).all()  # contiguous
    assert (slot[..., 0] == 0).all()
    counts = a.sum(2)
    assert torch.equal(counts > 0, seg.valid)  # a valid slot holds >= 1 step; slots are used in order
    assert (seg.valid.sum(-1) == slot[..., -1] + 1).all()  # the last used slot ends at T
    first = torch.where(seg.valid, seg.start, -1)
    expected = torch.stack([(slot == k).float().argmax(-1) for k in range(a.shape[-1])], -1)
    assert torch.equal(first[seg.valid], expected[seg.valid])  # latents are read at the slot's first step
    assert seg.valid.sum(-1).float().mean() > 1.2  # the test exercises real splits


def test_short_segments_are_not_forced_into_one_last_slot():
    """A head that cuts the shortest segments: every step after the burn-in is its own slot to the clip's end."""
    t = 30
    h = torch.randn(2, 6, t, 8)
    dur = LearnedDuration(rnn_hidden=8, hidden=8, burn_in=5).eval()
    with torch.no_grad():
        dur.head[-1].weight.zero_()
        dur.head[-1].bias.copy_(torch.tensor([-20.0, -5.0]))  # rho = 0: one-step slots
    lengths = dur.segment(h, h, torch.zeros(2, t + 1, 3, 4)).num_steps_per_slot
    assert lengths.shape[-1] == 1 + (t - 4) and (lengths[..., 1:] == 1).all()  # the burn-in span, then steps


def test_unit_durations_reproduce_dnri_exactly(make_cfg):
    dnri = build(make_cfg, "model=dnri").train()
    dider = build(make_cfg, "model=dider_paper", "model.net.duration.fixed_duration=1",  # and DNRI's objective
                  "model/net/objective=dnri").train()
    missing, unexpected = dider.load_state_dict(dnri.state_dict(), strict=False)
    assert not unexpected and all(k.startswith("duration.") for k in missing)
    batch = clip()
    torch.manual_seed(5)
    a = dnri.infer(batch, hard=False)
    torch.manual_seed(5)
    b = dider.infer(batch, hard=False)
    assert torch.equal(a.pred, b.pred)
    assert torch.equal(a.terms["nll"], b.terms["nll"]) and torch.equal(a.terms["kl_edge"], b.terms["kl_edge"])
    assert torch.equal(b.terms["kl_duration"], torch.zeros_like(b.terms["kl_duration"]))
    la, lb = dnri.loss(a)["loss"], dider.loss(b)["loss"]
    assert torch.equal(la, lb)


@pytest.mark.parametrize("model", ["dider_paper", "dider_paper_skid"])
def test_gradients_reach_the_duration_heads(make_cfg, model):
    net = build(make_cfg, f"model={model}").train()
    terms = net.loss(net.infer(clip(), hard=False))
    # the reconstruction alone (no KL) must move the boundaries: the straight-through path works
    terms["nll"].backward(retain_graph=True)
    grads = [p.grad for p in net.duration.parameters()]
    assert all(g is not None for g in grads) and sum(g.abs().sum() for g in grads) > 0
    net.zero_grad()
    terms["kl_duration"].backward()
    assert sum(p.grad.abs().sum() for p in net.duration.parameters()) > 0


@pytest.mark.parametrize("model", ["dider", "dider_skid", "dider_paper", "dider_paper_skid", "dnri", "dider_gate"])
def test_evaluation_is_deterministic(make_cfg, model):
    net = build(make_cfg, f"model={model}").eval()
    batch = clip()
    runs = []
    for _ in range(2):
        torch.manual_seed(11)
        out = net.infer(batch, hard=True)
        pred, types = net.rollout(batch["states"], batch["mask"], 5, 20)
        runs.append((out.pred, out.posterior_types(), pred, types))
    for x, y in zip(*runs, strict=True):
        assert torch.equal(x, y)


def test_online_duration_reads_only_the_past():
    """DIDER's segmentation of steps < t is fixed by the forward states up to t (which see x_0..x_t
    only: test_model.py); SKID's reads the reverse states and changes with the future."""
    torch.manual_seed(0)
    t, cut = 25, 12
    h_fwd, h_rev = torch.randn(3, 6, t, 8), torch.randn(3, 6, t, 8)
    h_fwd2, h_rev2 = h_fwd.clone(), torch.randn(3, 6, t, 8)  # the future changed: all reverse states move
    h_fwd2[:, :, cut:] = torch.randn(3, 6, t - cut, 8)
    for source, causal in (("past", True), ("future", False)):
        torch.manual_seed(1)  # prior_mu 0: long segments, as many slots for both
        dur = LearnedDuration(rnn_hidden=8, hidden=8, source=source, prior_mu=0.0).eval()
        a = dur.segment(h_fwd, h_rev, torch.zeros(1)).assign[:, :, :cut]
        b = dur.segment(h_fwd2, h_rev2, torch.zeros(1)).assign[:, :, :cut]
        assert torch.equal(a, b) == causal, source


@pytest.mark.parametrize("model", ["dider", "dider_skid", "dider_paper", "dider_paper_skid", "dider_gate"])
def test_rollout_and_online_types_are_causal(make_cfg, model):
    net = build(make_cfg, f"model={model}", "model/net/decoder=recurrent").eval()
    if model == "dider_gate":  # a prior gate that fires at some steps and not at others
        with torch.no_grad():
            logits = net.duration.prior(net.encoder(clip()["states"]).h_fwd)
            net.duration.prior[-1].bias.sub_(logits.median())
            fires = net.duration.prior(net.encoder(clip()["states"]).h_fwd) > 0
        assert 0 < fires.float().mean() < 1
    batch = clip(t=30)
    changed = batch["states"].clone()
    changed[:, 8:] = torch.rand_like(changed[:, 8:])
    outs = []
    for states in (batch["states"], changed):
        torch.manual_seed(3)
        pred, types = net.rollout(states, batch["mask"], 8, 20)
        online = net.online_types(net.encoder(states, batch["mask"]).h_fwd)
        outs.append((pred, types, online[..., :8]))
    for a, b in zip(*outs, strict=True):
        assert torch.equal(a, b)


def test_rollout_holds_types_for_their_duration(make_cfg):
    net = build(make_cfg, "model=dider_paper", "model.net.rollout_edges=argmax").eval()
    with torch.no_grad():
        net.duration.head[-1].bias.copy_(torch.tensor([5.0, 0.0]))  # rho -> 1: one segment to the end
    _, types = net.rollout(clip()["states"], clip()["mask"], 5, 20)
    # the burn-in's transitions 0..3 are one segment; the forecast's first segment runs to the end
    assert (types[..., :4] == types[..., :1]).all() and (types[..., 4:] == types[..., 4:5]).all()
    with torch.no_grad():
        net.duration.head[-1].bias.copy_(torch.tensor([-50.0, 0.0]))  # rho -> 0: one-step segments
    online = net.online_types(net.encoder(clip()["states"], clip()["mask"]).h_fwd)
    prior = net.prior(net.encoder(clip()["states"], clip()["mask"]).h_fwd).argmax(-1)
    assert torch.equal(online[..., 4:], prior[..., 4:]) and torch.equal(online[..., :4], prior[..., :1].expand_as(
        online[..., :4]))


@pytest.mark.parametrize("model", ["dider_paper", "dider_paper_skid"])
def test_first_forecast_segment_starts_after_the_burn_in(make_cfg, model):
    """The paper's t_1 = 0, d_0 = T_obs: the burn-in is its own segment, and the first forecast segment's
    type and duration are read at its end, in training (segment) and in the roll-out alike."""
    burn = 6
    net = build(make_cfg, f"model={model}", f"protocol.burn_in={burn}", "model.net.rollout_edges=argmax").eval()
    batch = clip(t=30)
    enc = net.encoder(batch["states"], batch["mask"])
    seg = net.duration.segment(enc.h_fwd, enc.h_rev, batch["states"])
    assert (seg.start[..., 0] == 0).all() and (seg.start[..., 1] == burn - 1).all()
    assert (seg.step_slot()[..., : burn - 1] == 0).all() and (seg.step_slot()[..., burn - 1] == 1).all()

    new_segment: dict[int, torch.Tensor] = {}  # t -> [B, E] bool: the edge starts a segment at t
    drawn: dict[int, torch.Tensor] = {}  # t -> [B, E] the duration a new segment would get
    latent: dict[int, torch.Tensor] = {}  # t -> [B, E] its latent's mean (durations are rounded to steps)
    advance, next_duration = net.advance_edges, net.duration.next_duration

    def spy_advance(h_t, t, end, etype, left, sample, *rest):
        new_segment[t] = left <= 0
        return advance(h_t, t, end, etype, left, sample, *rest)

    def spy_duration(h_t, t, end):
        drawn[t], latent[t] = next_duration(h_t, t, end), net.duration.gaussian(h_t)[0]
        return drawn[t]

    net.advance_edges, net.duration.next_duration = spy_advance, spy_duration
    changed = batch["states"].clone()
    changed[:, burn - 1] = torch.rand_like(changed[:, burn - 1]) * 2 - 1  # the last burn-in frame only
    runs = []
    for states in (batch["states"], changed):
        types = net.rollout(states, batch["mask"], burn, 10)[1]
        runs.append((types, dict(drawn), dict(new_segment), dict(latent)))
    (types_a, dur_a, new_a, mu_a), (types_b, _, _, mu_b) = runs
    # every edge starts a segment at transition 0 and where the forecast starts, never inside the burn-in
    assert [t for t in range(burn) if new_a[t].any()] == [0, burn - 1]
    assert new_a[0].all() and new_a[burn - 1].all() and (dur_a[0] == burn - 1).all()
    assert torch.equal(types_a[..., : burn - 1], types_b[..., : burn - 1])  # read at x_0: unchanged
    assert not torch.allclose(mu_a[burn - 1], mu_b[burn - 1])  # SKID online: its head on the past state
    assert not torch.equal(types_a[..., burn - 1], types_b[..., burn - 1])


def test_bad_duration_values_name_the_key():
    with pytest.raises(ValueError, match="LearnedDuration: source='sideways'"):
        LearnedDuration(source="sideways")


def test_duration_head_starts_at_the_prior_mean_with_sigma_init():
    dur = LearnedDuration(rnn_hidden=8, hidden=8, prior_mu=-0.6, sigma_init=0.2)
    with torch.no_grad():
        dur.head[-1].weight.zero_()  # the bias alone: what the head says before it has seen anything
    mu, sigma = dur.gaussian(torch.randn(3, 8))
    assert torch.allclose(mu, torch.full_like(mu, -0.6), atol=1e-6)
    assert torch.allclose(sigma, torch.full_like(sigma, 0.2), atol=1e-6)
    with pytest.raises(ValueError, match="LearnedDuration: sigma_init=0.005: must lie in"):
        LearnedDuration(sigma_init=0.005)


