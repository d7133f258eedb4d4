"""On a CUDA device: one short training end to end, and a bf16 training step whose edge and segment
arithmetic stays in fp32. Skipped without CUDA (``gpu`` marker, tests/conftest.py)."""

import math

import pytest
import torch

from dider.models.plugins import Progress
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
