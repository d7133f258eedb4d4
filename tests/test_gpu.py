"""On a CUDA device: one short training end to end, and a bf16 training step whose edge and segment
arithmetic stays in fp32. Skipped without CUDA (``gpu`` marker, tests/conftest.py)."""

import math

import pytest
import torch
from torch import nn

from dider.models.hazard import hold_assignment
from dider.models.plugins import Progress
from dider.models.rnn import bidirectional_lstm
from dider.models.vae import RelationalVAE
from dider.run import train

pytestmark = pytest.mark.gpu


def test_short_training_on_the_gpu(make_cfg, tmp_path):
    metrics = train(make_cfg(["trainer.accelerator=gpu", "trainer.devices=1", "trainer.max_epochs=2",
                              "logger=none"], out=tmp_path / "run"))
    assert all(math.isfinite(v) for k, v in metrics.items() if k.startswith("test/mse/"))
    assert (tmp_path / "run" / "metrics.json").is_file()


@pytest.mark.parametrize("model", ["dider", "dnri"])
def test_bf16_step_on_the_gpu(make_cfg, model):
    torch.manual_seed(0)
    net = RelationalVAE.from_config(make_cfg([f"model={model}"]).model).cuda().train()
    g = torch.Generator().manual_seed(0)
    batch = {"states": (torch.rand(4, 20, 3, 4, generator=g) * 2 - 1).cuda(),
             "mask": torch.ones(4, 20, 3, dtype=torch.bool).cuda()}
    with torch.autocast("cuda", dtype=torch.bfloat16):
        out = net.infer(batch, hard=False)
        terms = net.loss(out, Progress(0, 100))
    assert out.probs.dtype == torch.float32 and terms["loss"].dtype == torch.float32
    terms["loss"].backward()
    grads = [p.grad for p in net.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


def test_the_gpu_paths_of_the_lstm_and_the_hold_assignment_equal_the_cpus():
    """On CUDA the encoder's LSTMs run as two cuDNN calls and the hold assignment as one cumulative product."""
    torch.manual_seed(0)
    fwd, rev, seq = nn.LSTM(8, 5), nn.LSTM(8, 5), torch.randn(7, 4, 8)
    on_cpu = bidirectional_lstm(seq, fwd, rev, fused=False)
    with torch.backends.cudnn.flags(enabled=True, allow_tf32=False):  # fp32 products, as on the CPU
        on_gpu = bidirectional_lstm(seq.cuda(), fwd.cuda(), rev.cuda())
    assert all(torch.allclose(a, b.cpu(), atol=1e-5) for a, b in zip(on_cpu, on_gpu, strict=True))
    gate = (torch.rand(2, 3, 9) < 0.3).float().index_fill(-1, torch.tensor([0]), 1.0).requires_grad_()
    weights = torch.randn(2, 3, 9, 9)
    grads = []
    for g, w in ((gate, weights), (gate.detach().cuda().requires_grad_(), weights.cuda())):
        assign = hold_assignment(g)
        (assign * w).sum().backward()
        grads.append((assign.detach().cpu(), g.grad.cpu()))
    assert torch.equal(grads[0][0], grads[1][0]) and torch.allclose(grads[0][1], grads[1][1], atol=1e-5)
