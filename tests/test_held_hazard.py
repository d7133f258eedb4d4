"""DIDER's segments as runs of one type: the end evaluation reads where it is decided, the prior hazard that reads
the held type and the segment's age, its fit at every step, the online rule."""

from __future__ import annotations

import math

import torch

from dider.models.end_categorical import decided_end
from dider.models.held_hazard import HeldHazard
from dider.models.segment_end import SegmentEnd
from helpers.models import build


def test_decided_end_by_hand():
    """Hazard logits over 6 steps from start 1: the first step after the start that passes 1/2 is 4; a fixed
    boundary at 3 comes first where it is one; with no hazard passing, the segment runs to the clip's end (6)."""
    logits = torch.tensor([9.0, -1.0, 0.1, -2.0, 3.0, -1.0])
    free = torch.zeros(6, dtype=torch.bool)
    assert decided_end(logits, torch.tensor(1), free, free).item() == 2  # sigmoid(0.1) > 1/2
    logits[2] = -0.1
    assert decided_end(logits, torch.tensor(1), free, free).item() == 4
    fixed = torch.zeros(6, dtype=torch.bool)
    fixed[3] = True
    assert decided_end(logits, torch.tensor(1), fixed, fixed).item() == 3
    assert decided_end(logits, torch.tensor(4), fixed, torch.zeros(6, dtype=torch.bool)).item() == 6
    # a fixed step that is no boundary (inside the burn-in) is passed over
    assert decided_end(logits.clone().fill_(-5), torch.tensor(0), fixed, torch.zeros(6, dtype=torch.bool)).item() == 6


def test_held_hazard_reads_the_type_and_the_age():
    """of_start for every start equals of_start per start; along a given cut reads the type held at t - 1 and the
    age since that segment's start; online, ``at`` reads the same."""
    torch.manual_seed(0)
    hazard = HeldHazard(rnn_hidden=8, hidden=8, num_types=3, held=True, rate_logit=-1.0)
    h = torch.randn(2, 4, 10, 8)
    steps = hazard.steps(h)
    every = hazard.of_start(steps, torch.arange(10))  # [B, E, S, K, T]
    start = torch.tensor([[0, 3, 7, 9], [2, 2, 5, 1]])
    one = hazard.of_start(steps, start)  # [B, E, K, T]
    index = start[..., None, None, None].expand(-1, -1, 1, 3, 10)
    assert torch.allclose(every.gather(2, index).squeeze(2), one)
    held = torch.tensor([0, 0, 2, 2, 2, 1, 1, 0, 0, 0]).expand(2, 4, 10)
    starts = torch.tensor([1, 0, 1, 0, 0, 1, 0, 1, 0, 0], dtype=torch.bool).expand(2, 4, 10)
    along = hazard.along(h, held, starts)
    t = 4  # the segment holding step 3 started at 2 with type 2: age 2
    want = steps[..., t, 2] + hazard.ages(torch.tensor(2))[2]
    assert torch.allclose(along[..., t], want)
    online = hazard.at(h[..., t, :], torch.full((2, 4), 2), torch.full((2, 4), 2))
    assert torch.allclose(online, want)


def test_the_boundary_fit_targets_the_held_types_changes():
    """With the prior hazard's logits fixed at 0, the fit is log 2 at every free present step, whatever the
    target; a step where the type changes and one where it does not cost alike, absent and fixed steps nothing."""
    plugin = SegmentEnd(rnn_hidden=8, hidden=8, num_types=2, burn_in=3)
    with torch.no_grad():
        for p in plugin.prior.parameters():
            p.zero_()
    held = torch.tensor([[[0, 0, 0, 1, 1, 0, 0, 0, 1, 1]]])
    present = torch.ones(1, 1, 10, dtype=torch.bool)
    present[..., 9] = False
    fit = plugin.boundary_fit(torch.randn(1, 1, 10, 8), held, present)
    free = 10 - 3 - 1  # steps 0-2 fixed (the burn-in's span and the forecast's start), step 9 absent
    assert fit.item() == torch.tensor(free * math.log(2) / 9).item()


def test_online_a_boundary_brings_another_type(make_cfg):
    """Where the held type's hazard fires, the roll-out's next type is the prior's best other type, and the
    segment's age starts again; where it does not, the type and the segment's start stay."""
    net = build(make_cfg, "model=dider")
    assert net.capabilities.held_type and net.capabilities.online_retype
    b, e = 2, 6
    h_t = torch.randn(b, e, net.duration.prior.past[0].in_features)
    etype, left = torch.ones(b, e, dtype=torch.long), torch.full((b, e), 20)
    start = torch.full((b, e), 5)
    with torch.no_grad():
        net.duration.prior.past[-1].bias.fill_(30.0)  # every type's hazard fires
        net.prior.net[-1].bias.copy_(torch.tensor([0.0, 50.0]))  # the prior wants type 1, the one held
        new, _, new_start = net.advance_edges(h_t, 10, 30, etype, left, sample=False, start=start)
    assert (new == 0).all() and (new_start == 10).all()
    with torch.no_grad():
        net.duration.prior.past[-1].bias.fill_(-30.0)  # no hazard fires
        same, _, same_start = net.advance_edges(h_t, 11, 30, etype, left, sample=False, start=start)
    assert (same == 1).all() and (same_start == 5).all()
