"""The hold gate (model=dider_gate): boundaries, the held types and their gradients, the KL terms, online use."""

import math

import pytest
import torch

from dider.graph import edge_index
from dider.models.gate import HoldGate, bernoulli_kl, hold_assignment
from dider.models.segments import entries
from dider.validation import ConfigError
from helpers.fixtures import comings_and_goings
from helpers.models import build as build_net
from helpers.models import clip


def build(make_cfg, *overrides):
    return build_net(make_cfg, "model=dider_gate", *overrides)


def constant_gates(gate: HoldGate, posterior: float, prior: float) -> None:
    """Both gates' logits fixed at the given values, whatever they read."""
    with torch.no_grad():
        for head, value in ((gate.posterior, posterior), (gate.prior, prior)):
            head[-1].weight.zero_()
            head[-1].bias.fill_(value)


def test_bernoulli_kl_hand_values():
    # KL(0.5 || 0.25) = 0.5 ln(0.5 / 0.25) + 0.5 ln(0.5 / 0.75)
    got = bernoulli_kl(torch.tensor([0.0]), torch.tensor([math.log(0.25 / 0.75)]))
    assert got.item() == pytest.approx(0.5 * math.log(2) + 0.5 * math.log(2 / 3), abs=1e-6)
    assert bernoulli_kl(torch.tensor([1.3]), torch.tensor(1.3)).item() == pytest.approx(0.0, abs=1e-7)


@pytest.mark.parametrize("closed", [False, True])
@pytest.mark.parametrize("grad", [True, False])
def test_hold_assignment_puts_each_step_in_the_last_boundarys_slot(grad, closed):
    gate = torch.tensor([[[1.0, 0, 1, 0, 0, 1, 1]]], requires_grad=grad)
    assign = hold_assignment(gate, closed)
    assert assign.shape == (1, 1, 7, 7)
    assert assign.argmax(-1).tolist() == [[[0, 0, 2, 2, 2, 5, 6]]]
    assert torch.equal(assign.sum(-1), torch.ones(1, 1, 7))  # exactly one-hot forward
    g = torch.Generator().manual_seed(0)
    random = (torch.rand(2, 3, 20, generator=g) < 0.3).float().index_fill(-1, torch.tensor([0]), 1.0)
    assert torch.equal(hold_assignment(random.requires_grad_(grad), closed), hold_assignment(random.detach()))


@pytest.mark.parametrize("closed", [False, True])
def test_hold_assignment_gradient_is_the_switch_at_each_step(closed):
    """z_t = b_t y_t + (1 - b_t) z_{t-1} with b = [1, 0, 1] and L = z_1 + z_2: dL/db_1 = y_1 - y_0 (switching at
    step 1), dL/db_2 = y_2 - z_1 = y_2 - y_0; a later boundary stops the gradient of an earlier one at it."""
    b = torch.tensor([1.0, 0.0, 1.0], requires_grad=True)
    y = torch.tensor([[0.5], [2.0], [-1.0]])  # one value per slot
    z = torch.einsum("ts,sf->tf", hold_assignment(b.view(1, 1, 3), closed)[0, 0], y)
    (z[1] + z[2]).sum().backward()
    assert b.grad[1:].tolist() == pytest.approx([2.0 - 0.5, -1.0 - 0.5])


@pytest.mark.parametrize("straight_through", [True, False])
def test_hold_assignment_closed_form_equals_the_recurrence(straight_through):
    """The unrolled product (the GPU's path) and the step-by-step recurrence (the CPU's): the same assignment and
    the same gradient, for straight-through gates (0 or 1 forward: zeros in every product) and soft ones."""
    g = torch.Generator().manual_seed(0)
    soft = torch.rand(3, 4, 30, generator=g, dtype=torch.float64)
    hard = (soft > 0.8).double().index_fill(-1, torch.tensor([0]), 1.0)
    gate = (hard + soft - soft.detach() if straight_through else soft).detach().requires_grad_()
    weights = torch.randn(3, 4, 30, 30, generator=g, dtype=torch.float64)
    loop, closed = hold_assignment(gate, closed=False), hold_assignment(gate, closed=True)
    assert torch.allclose(loop, closed, rtol=0, atol=1e-12)
    grads = [torch.autograd.grad((a * weights).sum(), gate)[0] for a in (loop, closed)]
    assert grads[0].abs().max() > 1 and torch.allclose(*grads, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("burn_in", [None, 6])
@pytest.mark.parametrize("training", [True, False])
def test_gate_segments_tile_the_clip_and_respect_the_burn_in(burn_in, training):
    torch.manual_seed(0)
    gate = HoldGate(rnn_hidden=8, hidden=8, burn_in=burn_in).train(training)
    constant_gates(gate, 0.0, 0.0)  # every free step fires with probability 1/2 in training
    h_fwd, h_rev = torch.randn(3, 6, 25, 8), torch.randn(3, 6, 25, 8)
    seg = gate.segment(h_fwd, h_rev, torch.zeros(1))
    assert torch.equal(seg.assign.detach().sum(-1), torch.ones(3, 6, 25))
    slot = seg.step_slot()
    assert (slot[..., 0] == 0).all() and torch.equal(seg.valid, slot.eq(torch.arange(25)))  # a slot starts at its step
    if burn_in is not None:  # one observed segment, then a segment at the first forecast transition
        assert (slot[..., : burn_in - 1] == 0).all() and (slot[..., burn_in - 1] == burn_in - 1).all()
    if training:  # the free steps fire about half the time
        free = seg.valid[..., 1 if burn_in is None else burn_in :].float().mean()
        assert 0.4 < free < 0.6
    else:  # logit 0 is not above 1/2: no boundary outside the forced ones
        assert seg.valid.sum(-1).tolist() == [[1 if burn_in is None else 2] * 6] * 3


def test_gate_kl_mixes_the_learned_prior_and_the_rate_over_the_free_steps():
    gate = HoldGate(rnn_hidden=8, hidden=8, rate=0.1, rate_mix=0.25, burn_in=6)
    q, p = 0.7, -1.2
    constant_gates(gate, q, p)
    t = 20
    seg = gate.segment(torch.randn(2, 6, t, 8), torch.randn(2, 6, t, 8), torch.zeros(1))
    per_step = 0.75 * bernoulli_kl(torch.tensor(q), torch.tensor(p)) + 0.25 * bernoulli_kl(
        torch.tensor(q), torch.tensor(math.log(0.1 / 0.9)))
    free = t - 6  # steps 0..5 are fixed: the first, the burn-in's and the forecast's first
    assert seg.kl.tolist() == pytest.approx([per_step.item() * free / t] * 2, rel=1e-5)


def test_gradients_reach_both_gates(make_cfg):
    net = build(make_cfg).train()
    terms = net.loss(net.infer(clip(), hard=False))
    for term, heads in (("nll", ["posterior"]), ("kl_edge", ["posterior"]), ("kl_duration", ["posterior", "prior"])):
        net.zero_grad()
        terms[term].backward(retain_graph=True)
        for head in heads:  # the reconstruction and the edge KL reach the boundaries through the straight-through gate
            assert sum(p.grad.abs().sum() for p in getattr(net.duration, head).parameters()) > 0, (term, head)


@pytest.mark.parametrize("burn_in", [None, 6])
def test_online_types_hold_until_the_prior_gate_fires(make_cfg, burn_in):
    over = [] if burn_in is None else [f"protocol.burn_in={burn_in}", "model.net.duration.burn_in=${protocol.burn_in}"]
    net = build(make_cfg, "model.net.rollout_edges=argmax", *over).eval()
    batch = clip()
    h_fwd = net.encoder(batch["states"], batch["mask"]).h_fwd
    prior = net.prior(h_fwd).argmax(-1)
    first = 0 if burn_in is None else burn_in - 1
    constant_gates(net.duration, 0.0, 20.0)  # fires at every step after the burn-in: DNRI's per-step types
    online = net.online_types(h_fwd)
    assert torch.equal(online[..., first:], prior[..., first:])
    assert (online[..., :first] == prior[..., :1]).all()
    constant_gates(net.duration, 0.0, -20.0)  # never fires: the types read at the forecast's start are held
    online = net.online_types(h_fwd)
    assert (online[..., first:] == prior[..., first : first + 1]).all()
    _, types = net.rollout(batch["states"], batch["mask"], 8, 15)
    assert (types[..., first:] == types[..., first : first + 1]).all()


@pytest.mark.parametrize(("key", "value"), [("rate", 0.0), ("rate_mix", 1.5), ("temperature", 0.0),
                                            ("online_threshold", 1.0)])
def test_bad_gate_values_name_the_key(key, value):
    with pytest.raises(ConfigError, match=f"HoldGate: {key}={value}"):
        HoldGate(**{key: value})


def test_entries_are_the_steps_after_an_absence():
    present = torch.tensor([[False, True, True, False, True], [True, True, False, False, True]])
    assert entries(present).tolist() == [[False, True, False, False, True], [False, False, False, False, True]]


@pytest.mark.parametrize("burn_in", [None, 6])
@pytest.mark.parametrize("posterior", [-20.0, 20.0])
def test_gate_segments_restart_where_an_edge_enters(burn_in, posterior):
    """Never firing, a segment still starts where an edge enters; always firing, none starts where it is
    absent; so every segment that holds a present step starts at one (its edge KL is counted)."""
    gate = HoldGate(rnn_hidden=8, hidden=8, burn_in=burn_in).eval()
    constant_gates(gate, posterior, 0.0)
    present = comings_and_goings()
    h = torch.randn(2, 6, 20, 8)
    seg = gate.segment(h, h, torch.zeros(1), present=present)
    entered = present & ~torch.nn.functional.pad(present[..., :-1], (1, 0), value=False)
    assert (seg.valid[entered]).all()  # a boundary wherever an edge enters
    assert not seg.valid[..., 1:][~present[..., 1:]].any()  # none where it is absent
    if posterior < 0:  # the gate never fires: besides step 0, the forecast's start and the entries, no boundary
        forced = entered.clone()
        forced[..., 0] = True
        if burn_in is not None:
            forced[..., burn_in - 1] |= present[..., burn_in - 1]
        assert torch.equal(seg.valid, forced)
    holds_present = torch.einsum("bets,bet->bes", seg.assign, present.float()) > 0
    assert present.gather(2, seg.start)[holds_present].all()


def test_gate_kl_counts_the_present_free_steps_over_the_present_steps():
    gate = HoldGate(rnn_hidden=8, hidden=8, rate=0.1, rate_mix=0.25)
    q, p = 0.7, -1.2
    constant_gates(gate, q, p)
    present = comings_and_goings()
    seg = gate.segment(torch.randn(2, 6, 20, 8), torch.randn(2, 6, 20, 8), torch.zeros(1), present=present)
    per_step = 0.75 * bernoulli_kl(torch.tensor(q), torch.tensor(p)) + 0.25 * bernoulli_kl(
        torch.tensor(q), torch.tensor(math.log(0.1 / 0.9)))
    entered = present & ~torch.nn.functional.pad(present[..., :-1], (1, 0), value=False)
    free = (present & ~entered)[..., 1:].flatten(1).sum(1)  # step 0 is fixed too
    expected = per_step * free / present.flatten(1).sum(1)
    assert seg.kl.tolist() == pytest.approx(expected.tolist(), rel=1e-5)


def test_online_types_restart_where_an_edge_enters(make_cfg):
    net = build(make_cfg, "model.net.rollout_edges=argmax").eval()
    batch = clip(t=21)
    h_fwd = net.encoder(batch["states"], batch["mask"]).h_fwd
    prior = net.prior(h_fwd).argmax(-1)  # [B, E, T]
    constant_gates(net.duration, 0.0, -20.0)  # never fires: only an entry starts a segment
    present = comings_and_goings(b=4)
    online = net.online_types(h_fwd, present)
    entered = present & ~torch.nn.functional.pad(present[..., :-1], (1, 0), value=True)
    assert entered.any()
    assert torch.equal(online[entered], prior[entered])  # a new type at the entry, from the prior there
    step = torch.arange(20)
    last_entry = torch.where(entered, step, 0).cummax(-1).values  # the start of the segment held at each step
    assert torch.equal(online, prior.gather(2, last_entry))


def test_rollout_tells_the_gate_where_an_edge_enters(make_cfg):
    net = build(make_cfg).eval()
    batch = clip(b=2, t=20)
    mask = batch["mask"].clone()
    mask[:, 10:13, 2] = False  # agent 2 leaves after the burn-in and comes back at frame 13
    seen: dict[int, torch.Tensor | None] = {}
    advance = net.advance_edges

    def spy(h_t, t, end, etype, left, sample, entered=None, *rest):
        seen[t] = entered
        return advance(h_t, t, end, etype, left, sample, entered, *rest)

    net.advance_edges = spy
    net.rollout(batch["states"], mask, 8, 12)
    send, recv = edge_index(3, torch.device("cpu"))
    touches_2 = (send == 2) | (recv == 2)
    assert torch.equal(seen[13], touches_2.expand(2, 6))
    assert not any(seen[t].any() for t in seen if t not in (0, 13) and seen[t] is not None)
