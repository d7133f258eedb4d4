"""On a CUDA device: one short training end to end, and a bf16 training step whose edge and segment
arithmetic stays in fp32. Skipped without CUDA (``gpu`` marker, tests/conftest.py)."""

import logging
import math

import pytest
import torch
from torch import nn

from dider.models.hazard import hold_assignment
from dider.models.plugins import Progress
from dider.models.rnn import bidirectional_lstm
from dider.models.vae import RelationalVAE
from dider.run import train
from dider.training.step_graph import StepGraph

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


def test_a_captured_step_reads_each_steps_inputs_and_keeps_the_gradients_in_place():
    """StepGraph on CUDA: two eager warm-up calls, then the capture; every replay computes from that call's tensor
    and scalar, and writes the gradient where the optimiser reads it; another shape runs eagerly."""
    w = torch.ones(3, device="cuda", requires_grad=True)

    def step(inputs, flags):
        if w.grad is not None:
            w.grad.zero_()
        loss = ((w - inputs["x"]) ** 2).sum() * inputs["s"]
        loss.backward()
        return {"loss": loss.detach()}

    graph = StepGraph(step, warmup=2)
    for i in range(6):
        x, s = torch.full((3,), float(i), device="cuda"), 0.5 * (i + 1)
        out = graph({"x": x}, {"s": s})
        assert out["loss"].item() == pytest.approx(3 * (1 - i) ** 2 * s)
        assert torch.allclose(w.grad, torch.full_like(w, 2 * (1 - i) * s))
    assert graph.graph is not None and graph.replays == 4 and graph.eager_calls == 2
    out = graph({"x": torch.zeros(1, device="cuda")}, {"s": 1.0})  # another shape: eagerly, on the same weights
    assert graph.eager_calls == 3 and graph.replays == 4 and out["loss"].item() == pytest.approx(3.0)


@pytest.mark.parametrize("model", ["dnri", "dider"])
def test_the_graphed_job_on_the_gpu_trains_as_the_eager_one(make_cfg, tmp_path, model, caplog):
    """A short job with the steps captured (cuda_graph=auto on a GPU) against the same job eagerly: the KL weight
    and the learning rate move during it, so a graph that kept its first step's values would drift."""
    base = ["trainer.accelerator=gpu", "trainer.devices=1", f"model={model}", "seed=3", "logger=none",
            "trainer.max_epochs=2", "data.num_train=136", "model.scheduler.step_size=1",
            "model.net.objective.kl_warmup=0.6"]
    eager = train(make_cfg([*base, "cuda_graph=false"], out=tmp_path / "eager"))
    with caplog.at_level(logging.INFO, logger="dider.training.step_graph"):
        graphed = train(make_cfg([*base, "cuda_graph=auto"], out=tmp_path / "graphed"))
    assert "captured as one CUDA graph" in caplog.text and "could not be captured" not in caplog.text
    finite = [k for k, v in eager.items() if math.isfinite(v)]
    assert "test/nll" in finite
    off = {k: (eager[k], graphed[k]) for k in finite if not math.isclose(eager[k], graphed[k], rel_tol=1e-3,
                                                                          abs_tol=1e-6)}
    assert not off
