import pytest
import torch

from dider.models.decoders import KinematicStep, MarkovDecoder, RecurrentDecoder
from helpers.models import build
from helpers.models import clip as random_clip


def clip(b=4, t=20, n=3, seed=0):
    return random_clip(b, t, n, seed)


@pytest.mark.parametrize("cls", [MarkovDecoder, RecurrentDecoder])
def test_decoder_teacher_forced_equals_steps(cls):
    torch.manual_seed(0)
    dec = cls(num_types=3, hidden=16).eval()
    x = torch.randn(2, 6, 4, 4)
    z = torch.softmax(torch.randn(2, 6, 12, 3), -1)
    full = dec(x, z)
    state = dec.init_state(2, 4, x)
    for t in range(6):
        out, state = dec.step(x[:, t], z[:, t], state)
        torch.testing.assert_close(out, full[:, t])


@pytest.mark.parametrize("masked", [False, True])
def test_multi_step_training_rolls_out_each_block_from_its_true_state(masked):
    """prediction_steps=P: the prediction of step t comes from the true state at the start of its block of P steps
    and the decoder's own predictions since, as a step-by-step roll-out of each block gives (the last block cut
    short); P = 1 is teacher forcing."""
    torch.manual_seed(0)
    dec = MarkovDecoder(num_types=3, hidden=16, prediction_steps=3).eval()
    x, z = torch.randn(2, 7, 4, 4), torch.softmax(torch.randn(2, 7, 12, 3), -1)
    mask = torch.rand(2, 7, 4) > 0.2 if masked else None
    out = dec(x, z, mask)
    for start in range(0, 7, 3):
        cur = x[:, start]
        for t in range(start, min(start + 3, 7)):
            cur, _ = dec.step(cur, z[:, t], None, None if mask is None else mask[:, t])
            torch.testing.assert_close(out[:, t], cur)
    dec.prediction_steps = 1
    torch.testing.assert_close(dec(x, z, mask)[:, 0], out[:, 0])
    assert not torch.allclose(dec(x, z, mask)[:, 1], out[:, 1])


@pytest.mark.parametrize("cls", [MarkovDecoder, RecurrentDecoder])
def test_kinematic_step_moves_positions_by_the_new_velocity(cls):
    """x_{t+1} = x_t + delta, then p += slope * v_{t+1} + offset; both start at 0 (the plain residual
    update, with no new weights in a default decoder's checkpoint), and teacher forcing equals the steps."""
    torch.manual_seed(0)
    plain, kin = cls(num_types=2, hidden=16).eval(), cls(num_types=2, hidden=16, kinematic=True).eval()
    assert set(kin.state_dict()) - set(plain.state_dict()) == {"kinematic.slope", "kinematic.offset"}
    kin.load_state_dict(plain.state_dict(), strict=False)
    x, z = torch.randn(2, 5, 3, 4), torch.softmax(torch.randn(2, 5, 6, 2), -1)
    base = plain(x, z)
    torch.testing.assert_close(kin(x, z), base)
    with torch.no_grad():
        kin.kinematic.slope.fill_(0.25)
        kin.kinematic.offset.fill_(-0.5)
    out = kin(x, z)
    torch.testing.assert_close(out[..., 2:], base[..., 2:])
    torch.testing.assert_close(out[..., :2], base[..., :2] + 0.25 * base[..., 2:] - 0.5)
    state = kin.init_state(2, 3, x)
    for t in range(5):
        step, state = kin.step(x[:, t], z[:, t], state)
        torch.testing.assert_close(step, out[:, t])
    with pytest.raises(ValueError, match=f"{cls.__name__}: kinematic='yes': expected true or false"):
        cls(num_types=2, hidden=16, kinematic="yes")


def test_kinematic_step_fits_the_kinematics_of_the_clips():
    """Positions that move by 0.04 * v_{t+1} - 0.01 a step (absent agents carry junk): the least-squares fit
    recovers both; constant velocities leave it unset."""
    g = torch.Generator().manual_seed(0)
    v = torch.rand(3, 12, 4, 2, generator=g) * 2 - 1
    p = torch.cumsum(0.04 * v - 0.01, dim=1)
    mask = torch.rand(3, 12, 4, generator=g) > 0.2
    x = torch.cat([p, v], dim=-1).masked_fill(~mask[..., None], 7.0)
    step = KinematicStep()
    assert step.fit(x, mask)
    assert float(step.slope) == pytest.approx(0.04, abs=1e-5) and float(step.offset) == pytest.approx(-0.01, abs=1e-5)
    flat = KinematicStep()
    assert not flat.fit(torch.cat([p, torch.ones_like(v)], dim=-1)) and float(flat.slope) == 0.0


@pytest.mark.parametrize("cls", [MarkovDecoder, RecurrentDecoder])
def test_type_zero_sends_no_message(cls):
    torch.manual_seed(0)
    dec = cls(num_types=2, hidden=16).eval()
    x = torch.randn(1, 5, 3, 4)
    none = torch.zeros(1, 5, 6, 2)
    none[..., 0] = 1
    x2 = x.clone()
    x2[:, :, 1:] += 1.0  # move the other agents: agent 0 must not notice without interactions
    torch.testing.assert_close(dec(x, none)[:, :, 0], dec(x2, none)[:, :, 0])
    inter = torch.zeros_like(none)
    inter[..., 1] = 1
    assert not torch.allclose(dec(x, inter)[:, :, 0], dec(x2, inter)[:, :, 0])


@pytest.mark.parametrize("model", ["dnri", "nri"])
@pytest.mark.parametrize("decoder", ["markov", "recurrent"])
def test_rollout_is_causal(make_cfg, model, decoder):
    """Changing frames after the burn-in never changes the forecast, nor any edge type."""
    net = build(make_cfg, f"model={model}", f"model/net/decoder={decoder}").eval()
    batch = clip()
    burn = 5
    torch.manual_seed(1)
    pred, types = net.rollout(batch["states"], batch["mask"], burn, 15)
    changed = batch["states"].clone()
    changed[:, burn:] = torch.randn_like(changed[:, burn:])
    torch.manual_seed(1)
    pred2, types2 = net.rollout(changed, batch["mask"], burn, 15)
    assert pred.shape == (4, 15, 3, 4) and types.shape == (4, 6, burn + 15 - 1)
    torch.testing.assert_close(pred, pred2)
    assert torch.equal(types, types2)
    # ...while changing a burn-in frame does change it
    changed[:, burn - 1] += 0.5
    torch.manual_seed(1)
    assert not torch.allclose(pred, net.rollout(changed, batch["mask"], burn, 15)[0])


def test_prior_is_causal_in_training_pass(make_cfg):
    """The prior at transition t depends on x_0..x_t only; the posterior also sees later frames."""
    net = build(make_cfg, "model=dnri").eval()
    batch = clip()
    enc = net.encoder(batch["states"], batch["mask"])
    later = dict(batch, states=batch["states"].clone())
    later["states"][:, 12:] += 1.0
    enc2 = net.encoder(later["states"], later["mask"])
    torch.testing.assert_close(net.prior(enc.h_fwd[:, :, :12]), net.prior(enc2.h_fwd[:, :, :12]))
    assert not torch.allclose(enc.posterior_logits[:, :, 10], enc2.posterior_logits[:, :, 10])


def test_a_transition_posterior_reads_the_transition_and_its_past_only(make_cfg):
    """``posterior_reads=transition``: the type of transition t -> t+1 depends on x_0..x_{t+1}: frames from t+2 on
    change none of the types up to t, and frame t+1 changes the type at t."""
    net = build(make_cfg, "model=dider", "model.net.encoder.posterior_reads=transition").eval()
    batch = clip()
    logits = net.encoder(batch["states"], batch["mask"]).posterior_logits
    for first in (12, 11):  # frames from 12 on: transitions 0..10 read none of them; from 11 on: 10 reads it
        later = batch["states"].clone()
        later[:, first:] += 1.0
        moved = net.encoder(later, batch["mask"]).posterior_logits
        if first == 12:
            torch.testing.assert_close(logits[:, :, :11], moved[:, :, :11])
        else:
            assert not torch.allclose(logits[:, :, 10], moved[:, :, 10])


def test_losses_finite_and_gradients_reach_every_plugin(make_cfg):
    net = build(make_cfg, "model=dnri").train()
    terms = net.loss(net.infer(clip(), hard=False))
    assert all(torch.isfinite(v) for v in terms.values())
    terms["loss"].backward()
    for name in ("encoder", "prior", "decoder"):
        grads = [p.grad for p in getattr(net, name).parameters() if p.requires_grad]
        assert grads and all(g is not None for g in grads), name
        assert sum(g.abs().sum() for g in grads) > 0, name


def test_static_duration_gives_one_type_per_edge(make_cfg):
    net = build(make_cfg, "model=nri").eval()
    out = net.infer(clip(), hard=True)
    types = out.posterior_types()
    assert (types == types[..., :1]).all()
    assert out.seg.start.shape[-1] == 1


def test_bad_model_values_name_the_key(make_cfg):
    with pytest.raises(Exception, match="num_edges=1"):  # the first plugin built with it says so
        build(make_cfg, "model.num_edges=1")
    with pytest.raises(Exception, match="RelationalVAE: gumbel_tau=0: must be > 0"):
        build(make_cfg, "model.net.gumbel_tau=0")
    with pytest.raises(Exception, match="PriorFit: weight=-1"):
        build(make_cfg, "model=dider", "model.net.objective.prior_fit.weight=-1")


@pytest.mark.parametrize("masked", [False, True], ids=["all_present", "masked"])
@pytest.mark.parametrize("decoder", ["markov", "recurrent"])
def test_checkpointing_keeps_loss_gradients_and_statistics(make_cfg, decoder, masked):
    """The memory savers only move work: the loss, every gradient and the batch norms' running statistics
    equal the plain model's. Dropout is on where both paths draw its masks in the same order (the encoder;
    the recurrent decoder, step by step either way), so the re-run must replay the first run's masks."""
    widths = [f"model/net/decoder={decoder}", "model/net/objective=dider",  # decoder dropout: no evidence to read
              "model.net.encoder.hidden=16", "model.net.encoder.rnn_hidden=8",
              "model.net.encoder.head_hidden=8", "model.net.prior.hidden=8", "model.net.decoder.hidden=16",
              "model.net.encoder.dropout=0.1", f"model.net.decoder.dropout={0.1 if decoder == 'recurrent' else 0.0}"]
    plain = build(make_cfg, *widths)
    saver = build(make_cfg, *widths, "model.net.encoder.checkpoint=true", "model.net.decoder.checkpoint=true")
    saver.load_state_dict(plain.state_dict())
    assert saver.encoder.checkpoint and saver.decoder.checkpoint and not plain.encoder.checkpoint
    batch = clip(b=3, t=9, n=4)
    if masked:  # agent 3 leaves half-way: the masked message and aggregation paths
        batch["mask"][:, 5:, 3] = False
    losses = []
    for model in (plain, saver):
        model.train()
        torch.manual_seed(1)  # the same Gumbel noise and dropout masks
        loss = model.loss(model.infer(batch, hard=False))["loss"]
        loss.backward()
        losses.append(loss.detach())
    torch.testing.assert_close(losses[1], losses[0], rtol=1e-6, atol=0.0)
    # Relative to each gradient's largest entry: the Markov decoder's checkpointed path sums its weight
    # gradients step by step rather than over the whole clip at once (measured: 1.3e-7 of the largest entry).
    params = dict(plain.named_parameters())
    for name, p in saver.named_parameters():
        expected = params[name].grad
        scale = expected.abs().max().item()
        torch.testing.assert_close(p.grad, expected, rtol=1e-6, atol=1e-6 * scale + 1e-12, msg=name)
    buffers = dict(plain.named_buffers())
    for name, b in saver.named_buffers():  # running statistics updated once per step, not again by the re-run
        torch.testing.assert_close(b, buffers[name], rtol=1e-6, atol=1e-7, msg=name)


def test_checkpoint_flags_must_be_booleans(make_cfg):
    with pytest.raises(Exception, match="GNNLSTMEncoder: checkpoint='yes'"):
        build(make_cfg, "model.net.encoder.checkpoint=yes")
    with pytest.raises(Exception, match="MarkovDecoder: checkpoint=1"):
        build(make_cfg, "model.net.decoder.checkpoint=1")


def test_prior_per_step_is_dnris_online_prior_and_dider_holds_its_segments(make_cfg):
    """``test/edge_acc/prior_per_step`` reads the prior at every step: for DNRI exactly its online types; for
    DIDER the online types hold each segment's type: the burn-in's through the burn-in, whatever the prior reads
    there, and after it a type until the prior reads another or the held type's hazard fires."""
    dnri = build(make_cfg, "model=dnri").eval()
    h = dnri.encoder(*clip(b=8).values()).h_fwd
    torch.testing.assert_close(dnri.online_types(h), dnri.prior(h).argmax(-1), rtol=0, atol=0)

    dider = build(make_cfg, "model=dider").eval()
    with torch.no_grad():  # a prior whose type follows the state, so per-step types vary within a segment
        dider.prior.net[-1].weight.normal_(0, 5.0)
        dider.prior.net[-1].bias.zero_()
    torch.manual_seed(1)
    h = torch.randn(8, 6, 20, dider.prior.net[0].in_features)  # a past that changes at every step
    held, per_step = dider.online_types(h), dider.prior(h).argmax(-1)
    observed = dider.capabilities.observed
    assert (held[..., :observed] == held[..., :1]).all()  # the burn-in is one segment
    assert not torch.equal(held[..., :observed], per_step[..., :observed])
    assert (held[..., observed:] != held[..., observed - 1 : -1]).any()  # segments end after it


def test_training_after_inference_in_the_same_process(make_cfg):
    """The edge indices are cached per agent count: first built under inference mode (an evaluation or a
    prediction first in the process), they must still serve a training step's backward."""
    from dider.graph import _edge_index

    _edge_index.cache_clear()
    model = build(make_cfg, "model=dnri")
    batch = clip(b=2, t=6, n=5)
    with torch.inference_mode():
        model.infer(batch, hard=True)
    model.loss(model.infer(batch, hard=False))["loss"].backward()
    assert all(p.grad is not None for p in model.encoder.parameters() if p.requires_grad)
