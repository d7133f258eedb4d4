"""The fast building blocks equal the straightforward maths they replace."""

import pytest
import torch
from torch import nn

from dider.graph import aggregate_to_receivers, edge_id, edge_index, edge_mask, num_agents, num_edges
from dider.models import rnn
from dider.models.layers import FlatBatchNorm, PairLinear, SumLinear, TypedLinear
from dider.models.rnn import bidirectional_lstm


def test_edge_order_is_sender_major():
    send, recv = edge_index(3)
    assert list(zip(send.tolist(), recv.tolist(), strict=True)) == [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)]
    for n in (2, 3, 7, 50):  # edge_id and num_agents invert edge_index and num_edges
        send, recv = edge_index(n)
        assert torch.equal(edge_id(send, recv, n), torch.arange(n * (n - 1)))
        assert num_agents(num_edges(n)) == n


def test_pair_linear_equals_linear_on_concat():
    torch.manual_seed(0)
    nodes, extra = torch.randn(2, 7, 4, 5), torch.randn(2, 7, 12, 3)
    layer = PairLinear(5, 6, extra_dim=3)
    send, recv = edge_index(4)
    cat = torch.cat([nodes[..., send, :], nodes[..., recv, :], extra], dim=-1)
    torch.testing.assert_close(layer(nodes, extra), cat @ layer.weight.T + layer.bias)


def test_aggregate_and_mask():
    e = torch.randn(3, 20, 2)
    send, recv = edge_index(5)
    expected = torch.stack([e[:, recv == j].sum(1) for j in range(5)], dim=1)
    torch.testing.assert_close(aggregate_to_receivers(e, 5), expected)
    mask = torch.tensor([[True, False, True, True, True]])
    em = edge_mask(mask)
    assert em.sum() == 12 and not em[0, (send == 1) | (recv == 1)].any()


def test_typed_linear_per_type():
    layer = TypedLinear(3, 4, 5)
    x = torch.randn(6, 3, 4)
    for k in range(3):
        torch.testing.assert_close(layer(x)[:, k], x[:, k] @ layer.weight[k] + layer.bias[k])


def test_flat_batchnorm_matches_torch():
    torch.manual_seed(0)
    ours, ref = FlatBatchNorm(8), nn.BatchNorm1d(8)
    with torch.no_grad():
        ours.weight.uniform_()
        ref.weight.copy_(ours.weight)
    x = torch.randn(4, 6, 8)
    torch.testing.assert_close(ours(x), ref(x.reshape(-1, 8)).view(x.shape))
    torch.testing.assert_close(ours.running_var, ref.running_var)
    torch.testing.assert_close(ours.running_mean, ref.running_mean)
    ours.eval(), ref.eval()
    torch.testing.assert_close(ours(x), ref(x.reshape(-1, 8)).view(x.shape))


def test_flat_batchnorm_gradient_through_a_transposed_view():
    torch.manual_seed(0)
    ours, ref = FlatBatchNorm(8), nn.BatchNorm1d(8)
    x = torch.randn(5, 7, 8)
    a, b = x.clone().requires_grad_(), x.clone().requires_grad_()
    w = torch.randn(7, 5, 8)  # the loss reads the output transposed, so its gradient arrives transposed
    (ours(a).transpose(0, 1) * w).sum().backward()
    (ref(b.reshape(-1, 8)).view(x.shape).transpose(0, 1) * w).sum().backward()
    torch.testing.assert_close(a.grad, b.grad)
    torch.testing.assert_close(ours.weight.grad, ref.weight.grad)


@pytest.mark.parametrize("fused", [True, False, None])
def test_bidirectional_lstm_equals_two_torch_lstms(fused):
    torch.manual_seed(0)
    fwd, rev = nn.LSTM(6, 5), nn.LSTM(6, 5)
    seq = torch.randn(9, 4, 6)  # [T, M, H]
    ours = bidirectional_lstm(seq.requires_grad_(), fwd, rev, fused)
    ref = fwd(seq)[0].transpose(0, 1), rev(seq.flip(0))[0].flip(0).transpose(0, 1)
    for a, b in zip(ours, ref, strict=True):
        torch.testing.assert_close(a, b)
    w = torch.randn(2, 4, 9, 5)
    grads = [torch.autograd.grad((torch.stack(out) * w).sum(), [seq, *fwd.parameters(), *rev.parameters()])
             for out in (ours, ref)]
    for a, b in zip(*grads, strict=True):
        torch.testing.assert_close(a, b)


def test_bidirectional_lstm_rejects_other_lstms():
    with pytest.raises(ValueError, match="single-layer"):
        bidirectional_lstm(torch.zeros(3, 2, 4), nn.LSTM(4, 5, num_layers=2), nn.LSTM(4, 5))


def test_bidirectional_lstm_fuses_only_large_cpu_inputs(monkeypatch):
    calls = []
    fused = rnn._fused
    monkeypatch.setattr(rnn, "_fused", lambda *args: calls.append(args[0].shape) or fused(*args))
    fwd, rev, seq = nn.LSTM(6, 5), nn.LSTM(6, 5), torch.randn(9, 4, 6)
    monkeypatch.setattr(rnn, "FUSED_MIN_WORK", 4 * 6 + 1)
    bidirectional_lstm(seq, fwd, rev)
    assert calls == []  # 4 sequences x width 6: ATen's LSTM
    monkeypatch.setattr(rnn, "FUSED_MIN_WORK", 4 * 6)
    bidirectional_lstm(seq, fwd, rev)
    assert calls == [seq.shape]


@pytest.mark.parametrize("out_dim", [1, 16])
def test_sum_linear_is_a_linear_with_its_parameters(out_dim):
    """SumLinear computes nn.Linear as products and a sum (the same bits on any vector width) and keeps nn.Linear's
    parameters, so checkpoints of either load into the other."""
    torch.manual_seed(0)
    head, linear = SumLinear(7, out_dim), nn.Linear(7, out_dim)
    linear.load_state_dict(head.state_dict())
    x = torch.randn(5, 7, 7)
    assert head(x).shape == (5, 7, out_dim)
    assert torch.allclose(head(x), linear(x), atol=1e-6)
    assert {k: v.shape for k, v in head.state_dict().items()} == {k: v.shape for k, v in linear.state_dict().items()}
