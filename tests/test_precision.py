"""bf16 autocast: the networks run in bf16, the edge and segment arithmetic stays in fp32, results stay writable."""

import json

import numpy as np
import pytest
import torch

from dider.models.vae import RelationalVAE
from dider.outputs.clips import write_clips_npz
from dider.perf import native_bf16
from dider.run import train
from helpers.models import clip


@pytest.mark.parametrize("model", ["dider", "dider_skid", "dnri", "dider_gate"])
def test_autocast_keeps_edge_and_segment_arithmetic_in_fp32(make_cfg, model):
    """Logits, probabilities, KL terms and the slots' boundaries in fp32: in bf16 a boundary near step 49 moves
    in quarter steps and the prior's small probabilities round away. The GNN itself does run in bf16."""
    torch.manual_seed(0)
    net = RelationalVAE.from_config(make_cfg([f"model={model}"]).model).train()
    batch = clip(b=3, t=20)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = net.infer(batch, hard=False)
        said = net.describe(net.infer(batch, hard=True), batch["mask"])
        bf16_inside = net.encoder.embed(batch["states"]).dtype
    assert bf16_inside == torch.bfloat16
    for name in ("posterior_logits", "prior_logits", "probs", "step_logits", "prior_step_logits"):
        assert getattr(out, name).dtype == torch.float32, name
    assert all(v.dtype == torch.float32 for v in out.terms.values()), {k: v.dtype for k, v in out.terms.items()}
    assert out.seg.kl.dtype == torch.float32
    if out.seg.assign is not None:
        assert out.seg.assign.dtype == torch.float32
    assert said["probs"].dtype == torch.float32 and said["step_probs"].dtype == torch.float32
    assert torch.isfinite(net.loss(out)["loss"])


def test_clips_npz_takes_bf16_tensors(tmp_path):
    path = tmp_path / "clips.npz"
    probs = torch.tensor([[0.25, 0.5]], dtype=torch.bfloat16)
    write_clips_npz(path, {"probs": probs, "mask": torch.ones(1, 2, dtype=torch.bool)}, {})
    with np.load(path, allow_pickle=False) as saved:
        assert saved["probs"].dtype == np.float16 and saved["probs"].tolist() == [[0.25, 0.5]]


@pytest.mark.skipif(not native_bf16("cpu"), reason="bf16 is emulated on this CPU (many times slower)")
def test_bf16_mixed_run_writes_its_results(make_cfg, tmp_path):
    """A whole run in bf16-mixed precision: training, test, exports (clips.npz once failed on bf16 arrays)."""
    out = tmp_path / "run"
    metrics = train(make_cfg(["trainer.precision=bf16-mixed", "trainer.max_epochs=2"], out=out))
    record = json.loads((out / "metrics.json").read_text())
    assert record["config"]["trainer"]["precision"] == "bf16-mixed"
    assert all(np.isfinite(v) for v in metrics.values() if not np.isnan(v))
    assert np.isfinite(metrics["test/mse/h15"]) and np.isfinite(metrics["test/edge_acc/posterior/none"])
    with np.load(out / "clips.npz", allow_pickle=False) as saved:
        assert np.isfinite(saved["probs"].astype(np.float32)).all()


@pytest.mark.parametrize("native", [True, False])
def test_default_precision_is_bf16_only_on_cpus_that_compute_it(make_cfg, monkeypatch, native):
    """trainer.precision's default: bf16-mixed on a CPU with native bf16, 32-true on one without and on GPUs;
    an explicit value and $DIDER_DEFAULT_PRECISION (which this suite sets to 32-true) win."""
    import dider.training.resolvers

    monkeypatch.delenv("DIDER_DEFAULT_PRECISION")
    monkeypatch.setattr(dider.training.resolvers, "native_bf16", lambda device: native)
    assert make_cfg([]).trainer.precision == ("bf16-mixed" if native else "32-true")  # accelerator=cpu (TINY)
    assert make_cfg(["trainer.accelerator=gpu"]).trainer.precision == "32-true"
    assert make_cfg(["trainer.precision=32-true"]).trainer.precision == "32-true"
    monkeypatch.setenv("DIDER_DEFAULT_PRECISION", "32-true")
    assert make_cfg([]).trainer.precision == "32-true"
    monkeypatch.setenv("DIDER_DEFAULT_PRECISION", "fp8")
    with pytest.raises(Exception, match="DIDER_DEFAULT_PRECISION='fp8': expected one of"):
        make_cfg([]).trainer.precision  # noqa: B018 - resolving is the check
