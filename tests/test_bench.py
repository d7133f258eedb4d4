"""The benchmark's derived figures: arithmetic counts, the matmul ceiling and the summary."""

import torch

from dider import bench


def test_gemm_case_reports_its_arithmetic():
    case = bench.Case("gemm/fp32", [], 1, 0, 0, iters=2, warmup=1, kind="gemm", settings={"dtype": "fp32"})
    record = bench.run_case(case, "cpu")
    m, k, n = bench.GEMM_SHAPE
    assert record["settings"]["gflop_per_step"] == 2 * m * k * n / 1e9
    assert record["gflops"] == record["settings"]["gflop_per_step"] / record["step_s"] > 0


def test_step_gflop_counts_without_training_the_model():
    torch.manual_seed(0)
    model = bench.build_model(["model=dnri", "model.encoder.hidden=16", "model.decoder.hidden=16"])[0].train()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    states = torch.rand(2, 6, 3, 4)
    batch = {"states": states, "mask": torch.ones(states.shape[:3], dtype=torch.bool)}
    gflop = bench.step_gflop(model, batch)
    # forward + backward of the encoder's first edge layer alone: [B*T*N, 16] x [16, 32], three products
    assert gflop > 3 * 2 * (2 * 6 * 3) * 16 * 32 / 1e9
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())  # weights, batch-norm stats


def test_summary_speedups_and_roofline():
    def rec(name, samples_per_s, gflop=None, gflops=None, batch=128):
        settings = {"batch": batch} | ({"gflop_per_step": gflop} if gflop else {})
        return {"name": name, "samples_per_s": samples_per_s, "step_s": batch / samples_per_s,
                "settings": settings} | ({"gflops": gflops} if gflops else {})

    records = [rec("gemm/fp32", 10.0, gflop=5.0, gflops=200.0, batch=1), rec("train/dnri/synth", 102.0, gflop=100.0),
               rec("train/dnri/synth/bf16", 153.0), rec("train/dider/synth", 51.0),
               {"name": "train/dnri/recurrent", "error": "killed"}]
    out = bench.summary(records)
    assert out["speedup_over_reference/train/dnri/synth"] == 2.0
    assert out["speedup_over_reference/train/dnri/synth/bf16"] == 3.0
    assert out["roofline/fp32/train/dnri/synth/max_samples_per_s"] == 128 * 200.0 / 100.0
    assert out["step_ratio/dider_over_dnri/synth"] == 2.0
    assert not any("recurrent" in key or "bf16/train" in key for key in out)  # failed or missing cases
