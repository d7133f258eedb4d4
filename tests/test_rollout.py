"""Forecast protocols: the window's burn-in (global) and each agent's own burn-in (per_agent, DNRI's inD)."""

from types import SimpleNamespace

import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from dider.evaluation.metrics import HorizonMSE
from dider.graph import edge_mask
from dider.models.vae import RelationalVAE
from dider.protocol import agent_horizons, burn_in_mask
from dider.training.module import RelationalVAEModule
from helpers import NO_SPARSITY

pytestmark = pytest.mark.usefixtures("one_thread")


def build(make_cfg, *overrides):
    torch.manual_seed(0)
    return RelationalVAE.from_config(make_cfg(list(overrides)).model)


def clip(b=3, t=30, n=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, t, n, 4, generator=g) * 2 - 1, torch.ones(b, t, n, dtype=torch.bool)


@torch.no_grad()
def reference_rollout(net, x, mask, burn_in, num_pred):
    """The roll-out as it was before per-agent burn-in existed (one burn-in for the whole window)."""
    b, n = x.shape[0], x.shape[2]
    end = burn_in + num_pred - 1
    sample = net.rollout_edges == "sample"
    h_past, enc_state = net.encoder.past(x[:, :burn_in], mask[:, :burn_in])
    etype = torch.zeros(b, h_past.shape[1], dtype=torch.long)
    left, start = torch.zeros_like(etype), torch.zeros_like(etype)
    dec_state = net.decoder.init_state(b, n, x)
    preds, types = [], []
    cur = x[:, 0]
    for t in range(end):
        m_t = mask[:, t]
        if t < burn_in:
            cur, h_t = x[:, t], h_past[:, :, t]
        else:
            h_t, enc_state = net.encoder.step(cur, enc_state, m_t)
        etype, left, start = net.advance_edges(h_t, t, end, etype, left, sample, start=start)
        types.append(etype)
        if t < burn_in - 1 and net.decoder.stateless:
            continue
        z_t = F.one_hot(etype, net.num_types).to(x.dtype) * edge_mask(m_t).unsqueeze(-1)
        out, dec_state = net.decoder.step(cur, z_t, dec_state, m_t)
        if t >= burn_in - 1:
            preds.append(out)
            cur = out
    return torch.stack(preds, dim=1), torch.stack(types, dim=2)


def old_horizon_mse(horizons, pred, target, mask):
    """HorizonMSE.update as it was: frame h - 1 of the prediction window is horizon h for every agent."""
    idx = torch.tensor([h - 1 for h in horizons])
    sq = (pred.index_select(1, idx) - target.index_select(1, idx)).pow(2).sum(-1)
    m = mask.index_select(1, idx).to(sq.dtype)
    return (sq * m).sum(dim=(0, 2)).double() / (m.sum(dim=(0, 2)) * pred.shape[-1]).double().clamp_min(1)


@pytest.mark.parametrize("model", ["dnri", "dider"])
@pytest.mark.parametrize("decoder", ["markov", "recurrent"])
@pytest.mark.parametrize("burn", [1, 5])
def test_full_masks_every_mode_equals_the_old_path(make_cfg, model, decoder, burn):
    """Synthetic-like data (every agent present throughout): both modes are bit-identical to the old roll-out,
    and per-agent horizons score exactly what the old metric scored."""
    net = build(make_cfg, f"model={model}", f"model/net/decoder={decoder}").eval()
    x, mask = clip()
    num_pred = x.shape[1] - burn
    outs = {}
    for mode in ("reference", "global", "per_agent"):
        torch.manual_seed(7)  # rollout_edges=sample draws Gumbel noise
        if mode == "reference":
            outs[mode] = reference_rollout(net, x, mask, burn, num_pred)
        else:
            outs[mode] = net.rollout(x, mask, burn, num_pred, mode)
    for mode in ("global", "per_agent"):
        assert torch.equal(outs[mode][0], outs["reference"][0]), mode
        assert torch.equal(outs[mode][1], outs["reference"][1]), mode
    pred, target, tmask = outs["per_agent"][0], x[:, burn:], mask[:, burn:]
    horizons = [1, 7, num_pred]
    horizon = agent_horizons(mask, burn)[:, burn:]
    assert torch.equal(horizon, torch.arange(1, num_pred + 1).view(1, -1, 1).expand_as(horizon))
    per_agent, glob = HorizonMSE(horizons), HorizonMSE(horizons)
    per_agent.update(pred, target, tmask, horizon)
    glob.update(pred, target, tmask)
    want = old_horizon_mse(horizons, pred, target, tmask)
    assert torch.equal(glob.compute(), want) and torch.equal(per_agent.compute(), want)


def late_entry(t=30, n=4, enter=10, leave=24):
    """Sample 0: agent 3 enters at frame ``enter``; agent 2 leaves after frame ``leave`` - 1. Absent: zeros."""
    x, mask = clip(b=2, t=t, n=n)
    mask[0, :enter, 3] = False
    mask[0, leave:, 2] = False
    return x * mask[..., None], mask


@pytest.mark.parametrize("model", ["dnri", "dider"])
@pytest.mark.parametrize("decoder", ["markov", "recurrent"])
def test_per_agent_burn_in_is_causal_for_a_late_agent(make_cfg, model, decoder):
    """An agent entering at frame 10 is observed on frames 10..14 (burn-in 5) and rolled out from there:
    its later states change no prediction and no edge type, while its burn-in states do."""
    net = build(make_cfg, f"model={model}", f"model/net/decoder={decoder}").eval()
    burn, enter = 5, 10
    x, mask = late_entry(enter=enter)
    num_pred = x.shape[1] - burn
    torch.manual_seed(3)
    pred, types = net.rollout(x, mask, burn, num_pred, "per_agent")
    assert pred.shape == (2, num_pred, 4, 4) and types.shape == (2, 12, burn + num_pred - 1)

    later = x.clone()
    later[0, enter + burn:, 3] = torch.rand_like(later[0, enter + burn:, 3]) * 2 - 1
    later[0, 24:, 2] = 5.0  # states of an agent that has left: never read either
    torch.manual_seed(3)
    pred2, types2 = net.rollout(later, mask, burn, num_pred, "per_agent")
    assert torch.equal(pred, pred2) and torch.equal(types, types2)

    inside = x.clone()
    inside[0, enter + burn - 1, 3] += 0.5  # its last burn-in frame: ground truth it is observed on
    torch.manual_seed(3)
    pred3, _ = net.rollout(inside, mask, burn, num_pred, "per_agent")
    first = (enter + burn) - burn  # prediction-window index of frame enter + burn: its 1st own step
    assert not torch.allclose(pred3[0, first, 3], pred[0, first, 3])
    # ...and the window's other agents were past their burn-in already: the global protocol would have
    # fed the late agent's prediction from frame 5 on, so its ground truth at frame 14 would not count.
    torch.manual_seed(3)
    glob, _ = net.rollout(x, mask, burn, num_pred, "global")
    torch.manual_seed(3)
    glob3, _ = net.rollout(inside, mask, burn, num_pred, "global")
    assert torch.equal(glob[0, first, 3], glob3[0, first, 3])


def test_first_scored_horizon_is_the_agents_first_own_prediction():
    burn, enter = 5, 10
    _, mask = late_entry(enter=enter)
    h = agent_horizons(mask, burn)
    assert h[0, enter + burn, 3] == 1 and h[0, enter + burn - 1, 3] == 0 and h[0, enter - 1, 3] == 0
    assert h[0, enter + burn + 6, 3] == 7
    assert torch.equal(h[1, burn:, 0], torch.arange(1, 26))  # present from frame 0: the global horizon
    assert torch.equal(h >= 1, mask & ~burn_in_mask(mask, burn))
    # An error only on the late agent's frame 15 shows up at horizon 1 and nowhere else.
    p = 30 - burn
    pred, target = torch.zeros(2, p, 4, 4), torch.zeros(2, p, 4, 4)
    pred[0, (enter + burn) - burn, 3] = 1.0  # prediction-window index of frame 15
    metric = HorizonMSE([1, 2, 15])
    metric.update(pred, target, mask[:, burn:], h[:, burn:])
    values = metric.compute()
    assert values[0] > 0 and values[1] == 0 and values[2] == 0
    # global scoring would have called it horizon 11
    glob = HorizonMSE([1, 11])
    glob.update(pred, target, mask[:, burn:])
    assert glob.compute()[0] == 0 and glob.compute()[1] > 0
    # counts: every agent present at its h-th own step counts once per horizon
    metric = HorizonMSE([1, 15, 16])
    metric.update(pred, target, mask[:, burn:], h[:, burn:])
    assert metric.count.tolist() == [8 * 4, 8 * 4, 7 * 4]  # the late agent's 16th own step: frame 30, outside


def test_model_takes_the_mode_from_the_protocol(make_cfg, tmp_path):
    """The module's forecast protocol is the config's ``protocol`` node (one interpolation, as the data's): the
    module is told, not fished from a trainer, and the checkpoint keeps it as one node."""
    for data, mode in [("synth", "global"), ("ind", "per_agent")]:
        net = RelationalVAEModule.from_config(make_cfg(["model=dnri", f"data={data}"]).model)
        assert net.protocol.burn_in_mode == mode and net.hparams.protocol["burn_in_mode"] == mode, data
        net._trainer = SimpleNamespace(datamodule=SimpleNamespace(burn_in_mode="sideways"))
        assert net.protocol.burn_in_mode == mode  # the attached data module is not asked
    dnri = OmegaConf.to_container(make_cfg(["model=dnri"]).model, resolve=True)
    with pytest.raises(Exception, match=r"model.protocol.burn_in_mode='sideways'"):
        RelationalVAEModule.from_config({**dnri, "protocol": {**dnri["protocol"], "burn_in_mode": "sideways"}})
    for data, mode in [("synth", "global"), ("basketball", "global"), ("ind", "per_agent"),
                       ("ind200", "per_agent"), ("round", "per_agent"), ("trajectories", "per_agent")]:
        cfg = make_cfg([f"data={data}"])
        assert cfg.protocol.burn_in_mode == cfg.model.protocol.burn_in_mode == mode, data


def test_ind_run_scores_per_agent_horizons(make_cfg, tmp_path, monkeypatch):
    """A tiny fit + test on inD-format files: the per-agent protocol is used and every horizon is scored."""

    from dider.evaluation.metrics import HorizonMSE as Metric
    from dider.run import train
    from helpers.fixtures import write_ind_root

    root = write_ind_root(tmp_path / "inD")
    seen = []
    original = Metric.update

    def spy(self, pred, target, mask, horizon=None):
        seen.append(horizon is not None)
        return original(self, pred, target, mask, horizon)

    monkeypatch.setattr(Metric, "update", spy)
    cfg = make_cfg(["data=ind", f"data.source.root={root}", "data.split=[2,1,1]", "data.windows.seq_len=20",
                    "protocol.horizons=[1,5,15]", "data.loader.batch_size=4", "data.loader.eval_batch_size=4",
                    "model=dnri",
                    "model/net/decoder=recurrent", *NO_SPARSITY, "logger=none", "callbacks=none"],
                   out=tmp_path / "run")
    metrics = train(cfg)
    assert seen and all(seen)
    for h in ("h01", "h05", "h15"):
        assert torch.isfinite(torch.tensor(metrics[f"test/mse/{h}"])), h


def test_nri_forecasts_with_the_edges_its_encoder_infers_from_the_burn_in(make_cfg):
    net = build(make_cfg, "model=nri", "model.net.rollout_edges=argmax").eval()

    class FollowsTheClip(torch.nn.Module):
        """A posterior head whose type depends on the clip: the sign of a feature, centred over the batch."""

        def forward(self, h: torch.Tensor) -> torch.Tensor:
            f = h[..., 0] - h[..., 0].mean()
            return torch.stack([f, -f], dim=-1)

    net.encoder.posterior_head = FollowsTheClip()
    x, mask = clip(b=32, t=30, seed=4)
    burn = 6
    _, types = net.rollout(x, mask, burn, 10)
    assert (types == types[..., :1]).all()  # one type per edge, held (a static graph)
    enc = net.encoder(x[:, :burn], None)
    want = enc.posterior_logits[:, :, 0].argmax(-1)  # NRI's readout: the (one) segment's first step
    assert torch.equal(types[..., 0], want)
    assert set(types.unique().tolist()) == {0, 1}  # they depend on the clip: not the fixed prior's type 0
    later = x.clone()
    later[:, burn:] = torch.rand_like(later[:, burn:])  # frames after the burn-in are never read
    assert torch.equal(net.rollout(later, mask, burn, 10)[1], types)
    prior_only = build(make_cfg, "model=nri", "model.net.rollout_edges=argmax", "model.net.forecast_edges=prior").eval()
    assert (prior_only.rollout(x, mask, burn, 10)[1] == 0).all()  # the old behaviour: [0.9, 0.1] prior argmax
