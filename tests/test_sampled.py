"""Sampled futures: K roll-outs per clip whose online edges are drawn from the prior, scored as the field scores
them (minADE_K, minFDE_K, a miss rate in data units)."""

from __future__ import annotations

import math

import pytest
import torch

from dider.evaluation.sampled import MinDisplacement, sampled_values
from helpers.models import build, clip

pytestmark = pytest.mark.usefixtures("one_thread")


def test_min_displacement_by_hand():
    """One clip, two agents, three predicted steps, two samples; the truth at the origin. Agent 0: sample 0 is 1
    off at every step, sample 1 is 3, 0, 2 off; agent 1: 4 off everywhere in both, and absent at step 3.
    h2: minADE = mean(min(1, 1.5), min(4, 4)) = 2.5, minFDE = mean(min(1, 0), 4) = 2, misses (> 1.5): agent 1.
    h3: agent 1 has no frame at h3: minADE over agent 0 alone = min(1, 5/3) = 1 (agent 1's steps up to h3 count
    too: min(4, 4) = 4, mean 2.5), minFDE over agent 0 alone = min(1, 2) = 1, no miss."""
    off = torch.tensor([[[1.0, 4.0], [1.0, 4.0], [1.0, 4.0]], [[3.0, 4.0], [0.0, 4.0], [2.0, 4.0]]])  # [K, P, N]
    pred = torch.zeros(1, 2, 3, 2, 4)
    pred[..., 0] = off
    mask = torch.ones(1, 3, 2, dtype=torch.bool)
    mask[0, 2, 1] = False
    metric = MinDisplacement([2, 3], miss_threshold=1.5)
    metric.update(pred, torch.zeros(1, 3, 2, 4), mask)
    ade, fde, miss = metric.compute().tolist()
    assert ade == pytest.approx([2.5, 2.5]) and fde == pytest.approx([2.0, 1.0]) and miss == pytest.approx([0.5, 0])
    values = sampled_values("test", metric, 2)
    assert set(values) == {f"test/{k}_2/h{h:02d}" for k in ("min_ade", "min_fde", "miss_rate") for h in (2, 3)}
    without = MinDisplacement([2])
    without.update(pred, torch.zeros(1, 3, 2, 4), mask)
    assert math.isnan(without.compute()[2, 0]) and "test/miss_rate_2/h02" not in sampled_values("test", without, 2)


def test_one_future_of_argmax_edges_is_the_forecast(make_cfg):
    """K = 1 without drawing: the model's own roll-out, bit for bit; K = 4 drawn: four forecasts of each clip, not all
    alike (the edges are drawn)."""
    net = build(make_cfg, "model=dider", "model.net.rollout_edges=argmax").eval()
    batch = clip(b=3, t=20)
    own = net.rollout(batch["states"], batch["mask"], 5, 15)[0]
    one = net.sample_futures(batch["states"], batch["mask"], 5, 15, samples=1, draw=False)
    assert one.shape == (3, 1, 15, 3, 4) and torch.equal(one[:, 0], own)
    torch.manual_seed(0)
    net.prior.net[-1].bias.data.zero_()  # a prior that hesitates: drawn edges differ between samples
    four = net.sample_futures(batch["states"], batch["mask"], 5, 15, samples=4)
    assert four.shape == (3, 4, 15, 3, 4) and not torch.equal(four[:, 0], four[:, 1])


def test_nris_sampled_futures_draw_the_burn_ins_edges(make_cfg):
    """NRI holds the burn-in posterior's edges for the whole roll-out: its sampled futures draw them from that
    posterior (one draw per future), where its own roll-out reads the argmax."""
    net = build(make_cfg, "model=nri", "model.net.rollout_edges=argmax").eval()
    batch = clip(b=3, t=20)
    alike = net.sample_futures(batch["states"], batch["mask"], 5, 15, samples=4, draw=False)
    assert all(torch.equal(alike[:, 0], alike[:, k]) for k in range(1, 4))
    torch.manual_seed(0)
    drawn = net.sample_futures(batch["states"], batch["mask"], 5, 15, samples=4)
    assert not all(torch.equal(drawn[:, 0], drawn[:, k]) for k in range(1, 4))


def test_a_test_pass_scores_the_sampled_futures(make_cfg, tmp_path):
    from dider.run import train

    metrics = train(make_cfg(["logger=none", "model=dider", "protocol.samples=3", "protocol.miss_threshold=0.1"],
                             out=tmp_path / "run"))
    for h in (1, 15, 25):
        assert math.isfinite(metrics[f"test/min_ade_3/h{h:02d}"]) and 0 <= metrics[f"test/miss_rate_3/h{h:02d}"] <= 1
        assert metrics[f"test/min_fde_3/h{h:02d}"] >= 0


def test_predict_and_the_api_give_sampled_futures(tmp_path):
    """predict.samples=K: forecast.csv holds the forecast (sample 0) and K sampled futures (1..K) of every agent that
    carries on; the API's forecast(samples=K) gives [K, S, steps, N, 2]."""
    import numpy as np
    import pandas as pd

    import dider
    from dider.run import predict, train
    from helpers.fixtures import write_trajectories
    from test_predict import TINY, compose_cfg

    write_trajectories(tmp_path / "train.npz", num=40, steps=16, agents=3)
    train(compose_cfg([*TINY, f"data.source.path={tmp_path / 'train.npz'}"], tmp_path / "run"))
    new = write_trajectories(tmp_path / "new.npz", num=5, steps=12, agents=3, seed=3)
    predict(compose_cfg([*TINY, "mode=predict", f"ckpt_path={tmp_path / 'run'}",
            f"data.source.path={tmp_path / 'new.npz'}",
                         "predict.forecast_steps=4", "predict.samples=3"], tmp_path / "pred"))
    table = pd.read_csv(tmp_path / "pred" / "predictions" / "forecast.csv")
    assert sorted(table["sample"].unique()) == [0, 1, 2, 3]
    assert len(table) == 4 * 5 * 3 * 4  # samples x clips x agents x steps
    futures = dider.load(tmp_path / "run").forecast(new["positions"], burn_in=5, steps=4, samples=3)
    assert futures.shape == (3, 5, 4, 3, 2) and np.isfinite(futures).all()
