"""The segment-end duration (model=dider): the end's categorical from hazards, its KL, the cut it draws, gradients."""

import math

import pytest
import torch

from dider.models.end_categorical import end_kl, end_log_probs, median_end, offset_features
from dider.models.segment_end import SegmentEnd
from dider.models.segments import forced_boundaries


def constant_hazards(plugin: SegmentEnd, posterior: float, prior: float) -> None:
    """Both hazards' logits fixed at the given values, whatever they read (the held type and age too)."""
    with torch.no_grad():
        plugin.out.weight.zero_()
        plugin.out.bias.fill_(posterior)
        plugin.prior.past[-1].weight.zero_()
        plugin.prior.past[-1].bias.fill_(prior)
        if plugin.prior.age is not None:
            plugin.prior.age.weight.zero_()
            plugin.prior.age.bias.zero_()


def fixed_of(t, observed=0, present=None, shape=(1, 1)):
    fixed, value = forced_boundaries(t, observed, torch.device("cpu"), present)
    return fixed.expand(*shape, t), value.expand(*shape, t)


def test_end_categorical_by_hand():
    """Hazard 1/2 at every free step; a fixed boundary at 3: from 0 the end is 1 (1/2), 2 (1/4) or, having
    survived both, the fixed boundary 3 (1/4); from 3 the end is 4 (1/2) or the clip's end 5 (1/2)."""
    fixed = torch.tensor([True, False, False, True, False]).view(1, 1, 5)
    logits = torch.zeros(1, 1, 5)
    q0 = end_log_probs(logits, torch.tensor([[0]]), fixed, fixed).exp()
    assert q0.view(-1).tolist() == pytest.approx([0, 0.5, 0.25, 0.25, 0, 0], abs=1e-6)
    q3 = end_log_probs(logits, torch.tensor([[3]]), fixed, fixed).exp()
    assert q3.view(-1).tolist() == pytest.approx([0, 0, 0, 0, 0.5, 0.5], abs=1e-6)
    # a step with no boundary allowed (inside the burn-in, an absent edge) passes the mass on
    fixed_1 = torch.tensor([True, True, False, False, False]).view(1, 1, 5)
    none_at_1 = end_log_probs(logits, torch.tensor([[0]]), fixed_1, fixed_1 & (torch.arange(5) == 0)).exp()
    assert none_at_1.view(-1).tolist() == pytest.approx([0, 0, 0.5, 0.25, 0.125, 0.125], abs=1e-6)


def test_end_categorical_is_a_distribution_for_any_hazards():
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(4, 6, 30, generator=g) * 3
    fixed, value = fixed_of(30, observed=4, shape=(4, 6))
    start = torch.randint(0, 30, (4, 6), generator=g)
    q = end_log_probs(logits, start, fixed, value).exp()
    assert torch.allclose(q.sum(-1), torch.ones(4, 6), atol=1e-5)
    after = torch.arange(31) > start.unsqueeze(-1)
    assert (q[~after] == 0).all()


def test_median_end_and_kl_by_hand():
    log_q = torch.tensor([[[0.1, 0.3, 0.2, 0.4]]]).log()
    assert median_end(log_q).item() == 2  # cumulative 0.1, 0.4, 0.6
    log_p = torch.tensor([[[0.25, 0.25, 0.25, 0.25]]]).log()
    want = sum(q * math.log(q / 0.25) for q in (0.1, 0.3, 0.2, 0.4))
    assert end_kl(log_q, log_p).item() == pytest.approx(want, abs=1e-6)
    assert end_kl(log_q, log_q).item() == pytest.approx(0.0, abs=1e-7)


@pytest.mark.parametrize("training", [True, False])
@pytest.mark.parametrize("burn_in", [None, 6])
def test_segments_tile_the_clip_and_respect_the_fixed_boundaries(training, burn_in):
    torch.manual_seed(0)
    plugin = SegmentEnd(rnn_hidden=8, hidden=8, burn_in=burn_in).train(training)
    h_fwd, h_rev = torch.randn(3, 6, 25, 8), torch.randn(3, 6, 25, 8)
    seg = plugin.segment(h_fwd, h_rev, torch.zeros(1))
    assert torch.equal(seg.assign.detach().sum(-1), torch.ones(3, 6, 25))  # exactly one slot per step
    slot = seg.step_slot()
    assert torch.equal(seg.valid, slot.eq(torch.arange(25)))  # a slot starts at its own step
    if burn_in is not None:  # the burn-in is one observed segment, then one starts at the first forecast step
        assert (slot[..., : burn_in - 1] == 0).all() and (slot[..., burn_in - 1] == burn_in - 1).all()
    assert torch.isfinite(seg.kl).all() and (seg.kl >= -1e-6).all()


def test_evaluation_reads_each_segments_median_or_decided_end():
    """Posterior hazard 0.2 at every free step: from each start the median end is 4 steps on (1 - 0.8^3 =
    0.488 < 1/2 <= 1 - 0.8^4); without a burn-in, boundaries at 4, 8, ..., 24 of 26 steps. Where it is decided (a
    hazard past 1/2), a hazard of 0.2 never ends a segment: one segment; a hazard of 0.6 ends each at the next
    step."""
    plugin = SegmentEnd(rnn_hidden=8, hidden=8, end_readout="median").eval()
    constant_hazards(plugin, math.log(0.2 / 0.8), 0.0)
    h_fwd, h_rev = torch.randn(2, 6, 26, 8), torch.randn(2, 6, 26, 8)
    seg = plugin.segment(h_fwd, h_rev, torch.zeros(1))
    assert seg.valid[0, 0].nonzero().view(-1).tolist() == [0, 4, 8, 12, 16, 20, 24]
    plugin.end_readout = "threshold"
    assert plugin.segment(h_fwd, h_rev, torch.zeros(1)).valid.sum(-1).eq(1).all()
    constant_hazards(plugin, math.log(0.6 / 0.4), 0.0)
    assert plugin.segment(h_fwd, h_rev, torch.zeros(1)).valid.all()


def test_held_mode_ends_an_undecided_interaction_at_its_mode():
    """Posterior hazard 0.2 at every step (none passes 1/2), 26 steps: from a start s, q(end = s + 1) = 0.2 and the
    mass left for the clip's end 0.8^(25 - s), so q(end)'s mode is the next step for s <= 17 (0.8^(25 - s) < 0.2
    needs 25 - s > 7.2). Edge 0 holds an interaction at every step: segments start at 0..18, and the one at 18 runs
    on (its mode is the clip's end: 0.8^7 = 0.21 > 0.2). Edge 1 holds "none":
    no decided end, one segment (as ``threshold`` reads every edge). Edge 2 holds an interaction at steps 0-2, then
    "none": boundaries at 0, 1, 2, 3 and the "none" segment from 3 runs on."""
    plugin = SegmentEnd(rnn_hidden=8, hidden=8).eval()
    assert plugin.end_readout == "held_mode"
    constant_hazards(plugin, math.log(0.2 / 0.8), 0.0)
    h_fwd, h_rev = torch.randn(1, 3, 26, 8), torch.randn(1, 3, 26, 8)
    interaction = torch.zeros(1, 3, 26, dtype=torch.bool)
    interaction[0, 0], interaction[0, 2, :3] = True, True
    types = torch.stack([~interaction, interaction], -1).float()
    for every_start in (True, False):
        plugin.sync_free = every_start
        valid = plugin.segment(h_fwd, h_rev, None, types=types).valid[0]
        assert valid[0].nonzero().view(-1).tolist() == list(range(19))
        assert valid[1].nonzero().view(-1).tolist() == [0]
        assert valid[2].nonzero().view(-1).tolist() == [0, 1, 2, 3]
    plugin.end_readout = "threshold"
    assert plugin.segment(h_fwd, h_rev, None, types=types).valid.sum(-1).eq(1).all()
    plugin.end_readout = "held_mode"  # without the posterior's types (NRI's burn-in edges): the threshold's ends
    assert plugin.segment(h_fwd, h_rev, None).valid.sum(-1).eq(1).all()


def test_duration_kl_is_the_exact_kl_of_each_segment():
    """One segment per edge (hazard ~0 under both): q puts all its mass on the clip's end. With rate_mix = 1 the
    KL is -log p(no boundary in 9 free steps) = -9 log(1 - rate), per edge-step."""
    plugin = SegmentEnd(rnn_hidden=8, hidden=8, rate=0.1, rate_mix=1.0).eval()
    constant_hazards(plugin, -30.0, 0.0)
    seg = plugin.segment(torch.randn(2, 6, 10, 8), torch.randn(2, 6, 10, 8), torch.zeros(1))
    assert seg.valid.sum(-1).eq(1).all()
    want = -9 * math.log(0.9) / 10  # per edge: one segment's KL over 10 steps
    assert seg.kl.tolist() == pytest.approx([want, want], rel=1e-4)
    # and with the learned prior alone, equal to the posterior: no KL
    plugin = SegmentEnd(rnn_hidden=8, hidden=8, rate_mix=0.0).eval()
    constant_hazards(plugin, 0.7, 0.7)
    seg = plugin.segment(torch.randn(2, 6, 10, 8), torch.randn(2, 6, 10, 8), torch.zeros(1))
    assert seg.kl.abs().max().item() < 1e-5


def test_every_candidate_end_gets_a_gradient_in_training():
    """The soft sample reaches the held assignment at every candidate end: a loss on the assignment sends a
    gradient to the posterior's features at steps after each drawn end, not only at the ends."""
    torch.manual_seed(0)
    plugin = SegmentEnd(rnn_hidden=8, hidden=8).train()
    h_fwd = torch.randn(2, 6, 20, 8, requires_grad=True)
    seg = plugin.segment(h_fwd, torch.randn(2, 6, 20, 8), torch.zeros(1))
    (seg.assign * torch.randn_like(seg.assign)).sum().backward()
    touched = h_fwd.grad.abs().sum(-1) > 0  # [B, E, T]
    assert touched[..., 1:].float().mean() > 0.9


def test_the_number_of_segments_has_a_gradient():
    """Each later segment's duration KL is weighted by its straight-through existence, the soft sample of the
    end that opens it. The draws' argmax does not depend on the temperature, so with the same noise the hard
    cut and the KL are the same at two temperatures, and only the existence path's gradient (d soft / d logit
    scales as 1 / temperature) tells them apart."""
    grads = []
    for temperature in (0.5, 2.0):
        torch.manual_seed(0)
        plugin = SegmentEnd(rnn_hidden=8, hidden=8, temperature=temperature).train()
        constant_hazards(plugin, 0.0, 0.0)
        torch.manual_seed(1)
        seg = plugin.segment(torch.randn(2, 6, 12, 8), torch.randn(2, 6, 12, 8), torch.zeros(1))
        seg.kl.sum().backward()
        grads.append((seg.valid.clone(), seg.kl.detach().clone(), plugin.out.bias.grad.item()))
    assert torch.equal(grads[0][0], grads[1][0]) and torch.allclose(grads[0][1], grads[1][1])
    assert grads[0][0].sum() > 2 * 12  # several segments per edge: the existence weights are in play
    assert abs(grads[0][2] - grads[1][2]) > 1e-3 * max(abs(grads[0][2]), 1e-6)


def test_cut_kl_is_minus_log_the_priors_probability_of_the_cut():
    plugin = SegmentEnd(rnn_hidden=8, hidden=8, rate=0.25, rate_mix=0.5)
    constant_hazards(plugin, 0.0, math.log(0.5))  # learned prior hazard 1/3
    gate = torch.tensor([[[True, False, True, False]]])
    free = torch.tensor([[[False, True, True, True]]])
    got = plugin.cut_kl(torch.randn(1, 1, 4, 8), torch.randn(1, 1, 4, 8), gate, free, torch.tensor([4.0]))
    learned = -(math.log(2 / 3) + math.log(1 / 3) + math.log(2 / 3))
    rate = -(math.log(0.75) + math.log(0.25) + math.log(0.75))
    assert got.item() == pytest.approx((0.5 * learned + 0.5 * rate) / 4, rel=1e-5)


def test_online_boundaries_follow_the_prior_hazard():
    plugin = SegmentEnd(rnn_hidden=8, hidden=8, burn_in=5, online_threshold=0.5)
    constant_hazards(plugin, 0.0, 2.0)
    h = torch.randn(2, 6, 8)
    assert not plugin.boundary(h, 4, 40).any() and plugin.boundary(h, 5, 40).all()
    constant_hazards(plugin, 0.0, -2.0)
    assert not plugin.boundary(h, 10, 40).any()
    assert plugin.next_duration(h, 2, 40).eq(2).all() and plugin.next_duration(h, 10, 40).eq(30).all()


def test_paper_duration_cut_kl_by_hand():
    """The paper's Gaussian fraction: a cut [0, 3) + [3, 10) of 10 steps needs z in (2*2/10 - 1, 2*3/10 - 1] for
    the first slot (3 of 10 remaining steps) and, the last, z > 2*6/7 - 1 (more than 6 of 7); the prior
    N(-0.6, 1) gives each its probability."""
    from dider.models.durations import LearnedDuration

    def cdf(z):
        return 0.5 * (1 + math.erf((z + 0.6) / math.sqrt(2)))

    dur = LearnedDuration(rnn_hidden=8, hidden=8, prior_mu=-0.6, prior_sigma=1.0)
    gate = torch.zeros(1, 1, 10, dtype=torch.bool)
    gate[..., [0, 3]] = True
    got = dur.cut_kl(torch.randn(1, 1, 10, 8), torch.randn(1, 1, 10, 8), gate, gate, torch.tensor([10.0]))
    want = -math.log(cdf(-0.4) - cdf(-0.6)) - math.log(1 - cdf(2 * 6 / 7 - 1))
    assert got.item() == pytest.approx(want / 10, rel=1e-5)


def test_the_offset_table_reads_what_the_offset_layer_would():
    """reads=remaining: W_at offset_features(t - s) taken from a per-clip table equals the layer applied to each
    candidate's offset (the table only changes the order of the arithmetic)."""
    torch.manual_seed(0)
    plugin = SegmentEnd(rnn_hidden=8, hidden=16, reads="remaining")
    feats, start = torch.randn(2, 3, 20, 16), torch.tensor([[0, 5, 19], [3, 12, 7]])
    offset = (torch.arange(20) - start.unsqueeze(-1)).clamp_min(0)
    table = plugin.candidates(feats)
    assert torch.allclose(table[offset], plugin.at(offset_features(offset)), atol=1e-6)
    s = plugin.start(feats.gather(2, start[..., None, None].expand(-1, -1, 1, 16)))
    direct = plugin.out(torch.nn.functional.elu(plugin.at(offset_features(offset)) + s)).squeeze(-1)
    assert torch.allclose(plugin.posterior_logits(feats, table, start), direct, atol=1e-5)
    every = plugin.posterior_logits(feats, table)  # [B, E, S, T]: each start's row is its segment's hazards
    assert torch.allclose(every.gather(2, start[..., None, None].expand(-1, -1, 1, 20)).squeeze(2), direct, atol=1e-5)


@pytest.mark.parametrize("training", [True, False])
def test_the_segment_loop_ends_whatever_the_numbers(training, monkeypatch):
    """NaN hazards (a diverged network) leave every drawn end where it starts unless a segment is made to end after
    its start: the loop makes at most T passes (one end is drawn per pass; counted here, so the old endless loop
    fails instead of hanging) and covers the clip."""
    import dider.models.segment_end as segment_end

    passes, real = [], segment_end.end_log_probs

    def counted(*args):
        passes.append(1)
        assert len(passes) <= 3 * 12, "the segment loop does not end"
        return real(*args)

    monkeypatch.setattr(segment_end, "end_log_probs", counted)
    plugin = SegmentEnd(rnn_hidden=8, hidden=8).train(training)
    with torch.no_grad():
        for p in plugin.parameters():
            p.fill_(float("nan"))
    seg = plugin.segment(torch.randn(2, 6, 12, 8), torch.randn(2, 6, 12, 8), torch.zeros(1))
    assert len(passes) <= 3 * 12  # the posterior, learned prior and fixed-rate ends: three per pass
    assert seg.assign.shape == (2, 6, 12, 12) and seg.valid[..., 0].all()


class SharedNoise(SegmentEnd):
    """Draws each segment's end with the noise of its start from one tensor [B, E, S, T+1], whichever path asks."""

    noise: torch.Tensor

    def gumbel(self, log_q, start):
        if start.dim() == 2:  # segment after segment: this pass's starts [B, E]
            index = start.clamp(max=self.noise.shape[2] - 1)[..., None, None].expand(-1, -1, 1, self.noise.shape[-1])
            return self.noise.gather(2, index).squeeze(2)
        return self.noise  # every start at once


@pytest.mark.parametrize("reads", ["position", "remaining"])
@pytest.mark.parametrize("burn_in", [None, 5])
@pytest.mark.parametrize("agents_come_and_go", [False, True])
@pytest.mark.parametrize("end_readout", ["held_mode", "threshold"])
def test_every_start_at_once_cuts_as_segment_after_segment(reads, burn_in, agents_come_and_go, end_readout):
    """The GPU's path (every candidate start at once, the chain by pointer jumping) and the CPU's (one pass per
    segment) give the same cut and duration KL in evaluation, and in training with the same noise per start the same
    draws, KL and gradients."""
    from helpers.fixtures import comings_and_goings

    torch.manual_seed(0)
    plugin = SharedNoise(rnn_hidden=8, hidden=16, reads=reads, burn_in=burn_in, rate=0.15, num_types=3,
                         end_readout=end_readout)
    h_fwd, h_rev = torch.randn(3, 6, 20, 8), torch.randn(3, 6, 20, 8)
    types = torch.randn(3, 6, 20, 3).softmax(-1)  # the posterior's types at each start, which the prior reads
    present = comings_and_goings(3, 6, 20) if agents_come_and_go else None
    plugin.noise = -torch.empty(3, 6, 20, 21).exponential_().log()
    cuts = []
    for every_start in (True, False):
        plugin.sync_free = every_start
        evaluated = plugin.eval().segment(h_fwd, h_rev, None, present=present, types=types)
        leaf = h_fwd.clone().requires_grad_()
        trained = plugin.train().segment(leaf, h_rev, None, present=present, types=types)
        ((trained.assign * torch.arange(20.0).view(1, 1, -1, 1)).sum() + trained.kl.sum()).backward()
        cuts.append((evaluated.weight, evaluated.kl, trained.weight.detach(), trained.kl.detach(), leaf.grad))
    assert torch.equal(cuts[0][0], cuts[1][0]) and torch.equal(cuts[0][2], cuts[1][2])
    for a, b in zip(cuts[0][1:], cuts[1][1:], strict=True):
        assert torch.allclose(a, b, atol=1e-6, rtol=1e-5)
    assert cuts[0][2].sum() > 2 * 3 * 6  # several segments per edge: the chain is exercised


def test_the_two_paths_draw_from_the_same_distribution():
    """Independent draws, 300 each: how often each step starts a segment agrees within 4 binomial standard errors."""
    torch.manual_seed(0)
    plugin = SegmentEnd(rnn_hidden=8, hidden=16, rate=0.2).train()
    h_fwd, h_rev = torch.randn(1, 2, 15, 8).expand(300, -1, -1, -1), torch.randn(1, 2, 15, 8).expand(300, -1, -1, -1)
    freq = []
    with torch.no_grad():
        for every_start in (True, False):
            plugin.sync_free = every_start
            freq.append(plugin.segment(h_fwd, h_rev, None).valid.float().mean(0))  # [E, T]
    se = (freq[0] * (1 - freq[0]) / 300).sqrt().clamp_min(1 / 300)
    assert ((freq[0] - freq[1]).abs() <= 4 * se * 2**0.5).all()
    assert 0.05 < freq[0][:, 1:].mean() < 0.95


def test_chain_from_zero_by_hand():
    from dider.models.end_categorical import chain_from_zero

    # ends of segments starting at 0..7: 0 -> 3 -> 4 -> 8 (the clip's end); 1, 2, 5, 6, 7 are never starts
    end = torch.tensor([3, 5, 6, 4, 8, 7, 8, 8])
    assert chain_from_zero(end).nonzero().view(-1).tolist() == [0, 3, 4]
    assert chain_from_zero(torch.arange(1, 41)).all()  # one-step segments: 40 of them, 6 rounds of jumps
