"""Segments where agents come and go: a slot that its edge enters part-way is split at the entry, in every
duration plugin, in training and online, so no type held while the edge is present is read where it is absent."""

import pytest
import torch

from dider.graph import edge_index, edge_mask
from dider.models.durations import LearnedDuration, StaticDuration
from dider.models.segments import Segmentation, entries
from dider.models.vae import RelationalVAE
from dider.protocol import fill_absent
from helpers.fixtures import comings_and_goings


def whole_clip(b: int, e: int, t: int) -> Segmentation:
    """One slot per edge over the whole clip (NRI's)."""
    return Segmentation(torch.zeros(b, e, 1, dtype=torch.long), torch.ones(b, e, 1, dtype=torch.bool),
                        torch.ones(b, e, t, 1), torch.zeros(b))


def test_split_at_by_hand():
    # edge 0 enters at step 3: two slots; edge 1's cut is at step 0, where its slot starts anyway: one slot
    cuts = torch.tensor([[[False, False, False, True, False, False], [True, False, False, False, False, False]]])
    seg = whole_clip(1, 2, 6).split_at(cuts)
    assert seg.step_slot().tolist() == [[[0, 0, 0, 1, 1, 1], [0, 0, 0, 0, 0, 0]]]
    assert seg.start.tolist() == [[[0, 3], [0, 5]]]  # a slot with no step starts at T-1
    assert seg.valid.tolist() == [[[True, True], [True, False]]]
    assert torch.equal(seg.assign.sum(-1), torch.ones(1, 2, 6))
    no_cut = torch.zeros_like(cuts)
    assert whole_clip(1, 2, 6).split_at(no_cut).assign.shape[-1] == 1


def test_split_at_renumbers_later_slots_and_keeps_the_boundary_gradients():
    # slots [0, 2), [2, 5), [5, 7) with continuous boundaries; a cut at step 3 splits the second
    bounds = torch.tensor([[[0.0, 1.6, 4.2, 7.0]]], requires_grad=True)
    dur = LearnedDuration(rnn_hidden=4, hidden=4)
    assign, _ = dur._assignment(bounds, 7, tau=0.5)
    seg = Segmentation(torch.tensor([[[0, 2, 5]]]), torch.ones(1, 1, 3, dtype=torch.bool), assign, torch.zeros(1))
    cuts = torch.zeros(1, 1, 7, dtype=torch.bool)
    cuts[..., 3] = True
    split = seg.split_at(cuts)
    assert split.step_slot().tolist() == [[[0, 0, 1, 2, 2, 3, 3]]]
    assert split.start.tolist() == [[[0, 2, 3, 5]]]
    values = torch.tensor([1.0, -1.0, 2.0, 0.5]).view(1, 1, 4, 1)
    split.spread(values).sum().backward()
    assert bounds.grad[..., 1:3].abs().min() > 0  # the soft steps still reach the inner boundaries


def slots_start_where_present(seg: Segmentation, present: torch.Tensor) -> None:
    """Every slot holding a present step starts at one, and a slot starts at every entry."""
    hard = seg.assign.detach()
    assert torch.equal(hard.sum(-1), torch.ones_like(present, dtype=hard.dtype))  # exactly one-hot
    holds_present = torch.einsum("bets,bet->bes", hard, present.float()) > 0
    assert present.gather(2, seg.start)[holds_present].all()
    slot = seg.step_slot()
    starts_here = seg.start.gather(2, slot) == torch.arange(present.shape[-1])
    assert starts_here[entries(present)].all()


@pytest.mark.parametrize("training", [True, False])
@pytest.mark.parametrize("burn_in", [None, 6])
def test_learned_slots_split_where_an_edge_enters_and_durations_stand(training, burn_in):
    present = comings_and_goings()
    assert entries(present).any()
    dur = LearnedDuration(rnn_hidden=8, hidden=8, prior_mu=0.2, burn_in=burn_in).train(training)
    h = torch.randn(2, 6, 20, 8)
    torch.manual_seed(0)
    plain = dur.segment(h, h, torch.zeros(1))
    torch.manual_seed(0)
    seg = dur.segment(h, h, torch.zeros(1), present=present)
    slots_start_where_present(seg, present)
    assert torch.equal(seg.kl, plain.kl)  # the same durations were drawn: the cut moves none of them
    boundary = plain.start.gather(2, plain.step_slot()) == torch.arange(20)
    split = seg.start.gather(2, seg.step_slot()) == torch.arange(20)
    assert torch.equal(split, boundary | entries(present))


def test_static_segment_is_one_per_stretch_of_presence():
    present = comings_and_goings()
    seg = StaticDuration().segment(torch.randn(2, 6, 20, 8), torch.randn(2, 6, 20, 8), torch.zeros(1), present=present)
    slots_start_where_present(seg, present)
    assert torch.equal(seg.valid.sum(-1), 1 + entries(present).sum(-1))


@pytest.mark.parametrize("model", ["dider", "dider_paper", "nri"])
def test_the_type_held_after_an_entry_is_read_there_and_its_kl_counts(make_cfg, model):
    torch.manual_seed(0)
    net = RelationalVAE.from_config(make_cfg([f"model={model}", "model.net.posterior_readout=start"]).model).eval()
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 21, 3, 4, generator=g) * 2 - 1
    mask = torch.ones(2, 21, 3, dtype=torch.bool)
    mask[0, :5, 2] = False  # agent 2 enters at frame 5 in clip 0, and leaves for frames 10-12 in clip 1
    mask[1, 10:13, 2] = False
    out = net.infer({"states": x, "mask": mask}, hard=True)
    present = edge_mask(mask[:, :-1]).transpose(1, 2)  # [B, E, T-1]
    entered = entries(present)
    assert entered.sum() == 8  # agent 2's four edges, once in each clip
    held = out.posterior_types()
    assert torch.equal(held[entered], out.step_logits.argmax(-1)[entered])  # read at the entry itself
    holds_present = torch.einsum("bets,bet->bes", out.seg.assign, present.float()) > 0
    assert present.gather(2, out.seg.start)[holds_present].all()  # so every such slot's edge KL is counted


def test_online_types_reread_at_an_entry_and_keep_the_duration(make_cfg):
    torch.manual_seed(0)
    net = RelationalVAE.from_config(make_cfg(["model=dider_paper", "model.net.rollout_edges=argmax"]).model).eval()
    present = comings_and_goings()
    h_fwd = torch.randn(2, 6, 20, net.duration.head[0].in_features)
    lefts: list[torch.Tensor] = []
    advance = net.advance_edges

    def spy(h_t, t, end, etype, left, sample, entered=None, **rest):
        lefts.append(left)
        return advance(h_t, t, end, etype, left, sample, entered, **rest)

    net.advance_edges = spy
    net.online_types(h_fwd)
    plain_lefts, lefts = torch.stack(lefts, -1), []
    online = net.online_types(h_fwd, present)
    assert torch.equal(torch.stack(lefts, -1), plain_lefts)  # the durations run as without the entries
    step = torch.arange(20)
    start = torch.where((plain_lefts <= 0) | entries(present), step, 0).cummax(-1).values
    assert entries(present).any() and not torch.equal(start, torch.where(plain_lefts <= 0, step, 0).cummax(-1).values)
    assert torch.equal(online, net.prior(h_fwd).argmax(-1).gather(2, start))  # read at a segment's start or an entry


def test_nri_forecasts_an_edge_that_enters_in_the_burn_in_with_the_type_read_at_its_entry(make_cfg):
    torch.manual_seed(0)
    net = RelationalVAE.from_config(make_cfg(["model=nri", "model.net.rollout_edges=argmax"]).model).eval()
    g = torch.Generator().manual_seed(1)
    x = torch.rand(3, 20, 3, 4, generator=g) * 2 - 1
    mask = torch.ones(3, 20, 3, dtype=torch.bool)
    mask[:, :3, 2] = False  # agent 2 enters at frame 3, inside the burn-in of 8 frames
    _, types = net.rollout(x, mask, 8, 5, mode="per_agent")
    x_obs = fill_absent(x[:, :8], mask[:, :8])  # what the roll-out's burn-in holds
    step_types = net.encoder(x_obs, mask[:, :8]).posterior_logits.argmax(-1)  # [B, E, 7]
    send, recv = edge_index(3, torch.device("cpu"))
    late = (send == 2) | (recv == 2)
    assert torch.equal(types[:, late], step_types[:, late, 3:4].expand(-1, -1, types.shape[-1]))
    assert torch.equal(types[:, ~late], step_types[:, ~late, :1].expand(-1, -1, types.shape[-1]))
