"""Scheduled sampling for the online prior (dider.models.prior_rollout): the share's schedule, the rolled-out frames
against the model's own roll-out, and what a training pass's prior reads."""

import pytest
import torch

from dider.models.plugins import Progress
from dider.models.prior_rollout import rolled_frames, rollout_share
from helpers.models import build, clip


def test_the_share_rises_from_its_start_to_one_at_the_end_and_is_0_without_a_length():
    assert rollout_share(None, Progress(900, 1000)) == 0.0
    assert rollout_share(0.25, Progress(100, 1000)) == 0.0
    assert rollout_share(0.25, Progress(625, 1000)) == pytest.approx(0.5)
    assert rollout_share(0.25, Progress(1000, 1000)) == pytest.approx(1.0)
    assert rollout_share(0.25, Progress(5000, None)) == 0.0  # a trained model, a pass outside a Trainer
    assert rollout_share(0.0, Progress(0, 1000)) == 0.0


@pytest.mark.parametrize("mode", ["global", "per_agent"])
def test_rolled_frames_are_the_truth_in_the_burn_in_and_the_roll_out_after(make_cfg, mode):
    net = build(make_cfg, "model=dider").eval()
    batch = clip(b=2, t=12)
    x, mask = batch["states"], batch["mask"]
    if mode == "per_agent":  # agent 2 enters at frame 3: its first 4 present frames are its own burn-in
        mask[:, :3, 2] = False
        x = x.masked_fill(~mask[..., None], 0.0)
    edges = torch.randint(0, 2, (2, 6, 11))
    got = rolled_frames(net, x, mask, edges, 4, mode)
    pred, types = net.rollout(x, mask, 4, 8, mode, edges=edges)
    assert torch.equal(types, edges)
    assert torch.equal(got[:, :4], x[:, :4])
    if mode == "global":
        assert torch.equal(got[:, 4:], pred)
    else:  # agent 2's frames 4-6 are still its burn-in: the truth; its later frames and the others' are predicted
        assert torch.equal(got[:, 4:7, 2], x[:, 4:7, 2]) and torch.equal(got[:, 7:, 2], pred[:, 3:, 2])
        assert torch.equal(got[:, 4:, :2], pred[:, :, :2])


def _prior_logits(net, progress, burn_in):
    torch.manual_seed(1)
    return net.infer(clip(b=3, t=12), False, progress, burn_in=burn_in).prior_step_logits


def test_a_training_pass_gives_the_prior_the_roll_out_after_the_burn_in_only(make_cfg):
    net = build(make_cfg, "model=dider", "model.net.prior_rollout=0.0", "model.net.encoder.batch_norm=false").train()
    truth = _prior_logits(net, Progress(0, 100), 4)  # share 0 at the first step: the true frames
    rolled = _prior_logits(net, Progress(100, 100), 4)  # share 1: every clip reads its roll-out
    assert torch.equal(_prior_logits(net, Progress(100, 100), None), truth)  # no burn-in given: nothing rolled
    assert torch.allclose(rolled[:, :, :4], truth[:, :, :4], atol=1e-6)  # transitions that see no prediction
    assert (rolled[:, :, 4:] - truth[:, :, 4:]).abs().amax() > 1e-3
    net.eval()  # validation and test: the true frames
    assert torch.equal(_prior_logits(net, Progress(100, 100), 4), _prior_logits(net, Progress(0, 100), 4))
    assert net.schedule(Progress(100, 100))["prior_rollout"] == pytest.approx(1.0)


def test_the_share_must_be_a_share_of_training(make_cfg):
    with pytest.raises(Exception, match="prior_rollout"):
        build(make_cfg, "model=dider", "model.net.prior_rollout=1.5")
