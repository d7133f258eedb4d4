"""The baseline models: constant velocity and the decoder without edges, through the same test loop."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dider.models.baselines import ConstantVelocity
from dider.models.vae import RelationalVAE
from dider.run import train


def test_constant_velocity_carries_the_last_displacement():
    x = torch.randn(2, 6, 3, 4)
    x[:, :, :, :2] = x[:, :, :, :2].cumsum(1)
    model = RelationalVAE.from_config({
        "_target_": "dider.models.vae.RelationalVAE", "num_edges": 2,
        "encoder": {"_target_": "dider.models.encoder.GNNLSTMEncoder", "num_types": 2, "hidden": 8,
                    "rnn_hidden": 8, "head_hidden": 8},
        "prior": {"_target_": "dider.models.prior.LearnedPrior", "num_types": 2, "rnn_hidden": 8, "hidden": 8},
        "duration": {"_target_": "dider.models.durations.PerStepDuration"},
        "decoder": {"_target_": "dider.models.baselines.ConstantVelocity"},
        "objective": {"_target_": "dider.models.objective.Objective",
                      "nll": {"_target_": "dider.models.likelihood.GaussianNLL"}}})
    pred = model.rollout(x, torch.ones(2, 6, 3, dtype=torch.bool), burn_in=3, num_pred=3)[0]
    step = x[:, 2, :, :2] - x[:, 1, :, :2]  # the last observed displacement
    for k in range(3):  # k + 1 displacements past the last observed frame; velocity features held
        torch.testing.assert_close(pred[:, k, :, :2], x[:, 2, :, :2] + (k + 1) * step)
        torch.testing.assert_close(pred[:, k, :, 2:], x[:, 2, :, 2:])


def test_constant_velocity_teacher_forced_and_masked():
    x = torch.arange(2 * 4 * 2 * 4, dtype=torch.float32).view(2, 4, 2, 4)
    mask = torch.ones(2, 4, 2, dtype=torch.bool)
    mask[0, 1, 1] = False  # agent 1 absent at frame 1: no displacement into frame 2
    out = ConstantVelocity()(x, torch.zeros(2, 4, 2, 2), mask)
    torch.testing.assert_close(out[:, 0], x[:, 0])  # the first frame has no displacement
    torch.testing.assert_close(out[1, 2, :, :2], 2 * x[1, 2, :, :2] - x[1, 1, :, :2])
    torch.testing.assert_close(out[0, 2, 1], x[0, 2, 1])


def test_static_decoder_ignores_the_edges(make_cfg):
    cfg = make_cfg(["model=static_decoder", "model/net/decoder=recurrent"])
    model = RelationalVAE.from_config(cfg.model).eval()
    x, mask = torch.randn(2, 8, 3, 4), torch.ones(2, 8, 3, dtype=torch.bool)
    edges = torch.randint(0, 2, (2, 6, 7))
    pred = model.rollout(x, mask, 3, 5, edges=edges)[0]
    torch.testing.assert_close(pred, model.rollout(x, mask, 3, 5, edges=1 - edges)[0])
    model.decoder_edges = True  # the same network with its edges on: they matter
    assert not torch.allclose(pred, model.rollout(x, mask, 3, 5, edges=1 - edges)[0])


@pytest.mark.parametrize("model", ["constant_velocity", "static_decoder"])
def test_baselines_run_through_the_test_loop(make_cfg, tmp_path, model):
    metrics = train(make_cfg([f"model={model}", "model/net/decoder=recurrent"], out=tmp_path / "run"))
    horizons = sorted(k.rsplit("/", 1)[1] for k in metrics if k.startswith("test/ade/h"))
    assert len(horizons) >= 2 and "test/mse/h01" in metrics
    ade, fde = (np.array([metrics[f"test/{m}/{h}"] for h in horizons]) for m in ("ade", "fde"))
    assert (0 < ade).all() and (ade <= fde).all() and (fde < float("inf")).all()  # errors grow along a roll-out
    cv = np.array([metrics[f"test/cv/ade/{h}"] for h in horizons])
    ratio = np.array([metrics[f"test/ade_vs_cv/{h}"] for h in horizons])
    np.testing.assert_allclose(ratio, ade / cv, rtol=1e-5)
    if model == "constant_velocity":  # scored against itself on the same clips and masks
        np.testing.assert_allclose(ratio, 1.0, rtol=1e-5)
