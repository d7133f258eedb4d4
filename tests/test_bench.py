"""The benchmark's derived figures: arithmetic counts, the matmul ceiling and the summary; the comparison
with the reference implementation timed in the same run."""

import json
import os
from pathlib import Path

import pytest
import torch

from dider.bench import cases as bench_cases
from dider.bench import cli as bench  # the command line's namespace: main, run_case, cases, ...
from dider.bench import reference as bench_reference
from dider.bench import steps as bench_steps

# A checkout of cgraber/cvpr_dNRI, named by $DIDER_DNRI_REFERENCE (the comparison is skipped without one).
REFERENCE_CHECKOUT = Path(os.environ.get("DIDER_DNRI_REFERENCE", "/nonexistent/cvpr_dNRI"))


def test_gemm_case_reports_its_arithmetic():
    case = bench.Case("gemm/fp32", [], 1, 0, 0, iters=2, warmup=1, kind="gemm", settings={"dtype": "fp32"})
    record = bench.run_case(case, "cpu")
    m, k, n = bench_cases.GEMM_SHAPE
    assert record["settings"]["gflop_per_step"] == 2 * m * k * n / 1e9
    assert record["gflops"] == record["settings"]["gflop_per_step"] / record["step_s"] > 0


def test_step_gflop_counts_without_training_the_model():
    torch.manual_seed(0)
    model = bench_steps.build_model(["model=dnri", "model.net.encoder.hidden=16",
                                     "model.net.decoder.hidden=16"])[0].train()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    states = torch.rand(2, 6, 3, 4)
    batch = {"states": states, "mask": torch.ones(states.shape[:3], dtype=torch.bool)}
    gflop = bench_steps.step_gflop(model, batch)
    # forward + backward of the encoder's first edge layer alone: [B*T*N, 16] x [16, 32], three products
    assert gflop > 3 * 2 * (2 * 6 * 3) * 16 * 32 / 1e9
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())  # weights, batch-norm stats


def test_summary_roofline_and_step_ratio_without_speedups():
    def rec(name, samples_per_s, gflop=None, gflops=None, batch=128):
        settings = {"batch": batch} | ({"gflop_per_step": gflop} if gflop else {})
        return {"name": name, "samples_per_s": samples_per_s, "step_s": batch / samples_per_s,
                "settings": settings} | ({"gflops": gflops} if gflops else {})

    records = [rec("gemm/fp32", 10.0, gflop=5.0, gflops=200.0, batch=1), rec("train/dnri/synth", 100.0, gflop=100.0),
               rec("train/dnri/synth/bf16", 150.0), rec("train/dider/synth", 50.0),
               {"name": "train/dnri/recurrent", "error": "killed"}]
    out = bench.summary(records)
    assert not any("over_reference" in key for key in out)  # without --reference: no speed-ups
    assert out["roofline/fp32/train/dnri/synth/max_samples_per_s"] == 128 * 200.0 / 100.0
    assert out["step_ratio/dider_over_dnri/synth"] == pytest.approx(2.0)
    assert not any("recurrent" in key or "bf16/train" in key for key in out)  # failed or missing cases


def test_allocator_ratios_pair_each_round_by_hand():
    """thresholds against heap: step times 1.0 / 1.1, 2.0 / 2.0 (a slow round), 1.0 / 1.3 -> ratios 1.1, 1.0, 1.3,
    median 1.1; a failed measurement drops its round's pair, and a plain run's records give nothing."""
    def rec(mode, round_, step, peak):
        return {"name": "train/x", "allocator": mode, "round": round_, "step_s": step, "peak_memory_mb": peak}

    records = [rec("heap", 0, 1.0, 110.0), rec("thresholds", 0, 1.1, 100.0),
               rec("thresholds", 1, 2.0, 100.0), rec("heap", 1, 2.0, 125.0),
               rec("heap", 2, 1.0, 100.0), rec("thresholds", 2, 1.3, 100.0),
               {**rec("heap", 3, 9.0, 1.0), "error": "killed"}, rec("thresholds", 3, 1.0, 100.0),
               {"name": "rollout/x", "allocator": "heap", "step_s": 1.0, "peak_memory_mb": 1.0}]
    out = bench.summary(records)
    assert out == {"allocator/thresholds_over_heap/train/x/step": pytest.approx(1.1),
                   "allocator/thresholds_over_heap/train/x/peak": pytest.approx(100 / 110)}


@pytest.mark.slow  # two real benchmark cases under each allocator setting
def test_allocator_comparison_runs_each_case_under_each_setting_in_turn(monkeypatch, tmp_path):
    """``--allocator heap thresholds``: every round runs the case once under each (fresh processes, the order
    reversed every other round), each record says the setting its process ran with, and the environment is
    restored after."""
    tiny = bench.REFERENCE_SIZES["tiny"]
    case = bench.Case("train/dnri/tiny", ["model=dnri", *tiny["overrides"]], tiny["batch"], 3, tiny["steps"],
                      iters=1, warmup=0)
    other = bench.Case("train/dnri/tiny/compile", [], 1, 3, 8)  # left out by --only's anchored expression
    monkeypatch.setattr(bench, "cases", lambda: [case, other])
    monkeypatch.setenv("DIDER_ALLOCATOR", "system")
    out = tmp_path / "b.json"
    bench.main(["--only", "dnri/tiny$", "--allocator", "heap", "thresholds", "--allocator-rounds", "2",
                "--out", str(out)])
    doc = json.loads(out.read_text())
    assert [(r["round"], r["allocator"]) for r in doc["records"]] == [
        (0, "heap"), (0, "thresholds"), (1, "thresholds"), (1, "heap")]
    assert bench._alternating(["a", "b", "c"], 3) == [(0, "a"), (0, "b"), (0, "c"), (1, "c"), (1, "b"), (1, "a"),
                                                     (2, "a"), (2, "b"), (2, "c")]
    assert doc["meta"]["allocator"] == ["heap", "thresholds"]
    assert {"allocator/thresholds_over_heap/train/dnri/tiny/step",
            "allocator/thresholds_over_heap/train/dnri/tiny/peak"} <= set(doc["summary"])
    assert os.environ["DIDER_ALLOCATOR"] == "system"
    assert {r["name"] for r in doc["records"]} == {"train/dnri/tiny"}
    for bad in (["--allocator", "heap", "heap"], ["--only", "train/(dnri"]):
        with pytest.raises(SystemExit):
            bench.main([*bad, "--out", str(out)])


def test_interleaved_rounds_alternate_and_pair_the_speedups():
    """Two fake steps on a fake clock: A costs 3 units, B 1; in round 2 the machine is twice as slow."""
    now, calls, current_round = [0.0], [], [0]

    def step(name, cost):
        def fn():
            calls.append(name)
            now[0] += cost * (2 if current_round[0] == 2 else 1)
        return fn

    steps = {"A": step("A", 3.0), "B": step("B", 1.0)}

    def clock():
        current_round[0] = (len(calls) - 2) // 4  # 2 warm-up calls, then 4 calls (2 x 2 iterations) a round
        return now[0]

    per_round = bench_reference.interleaved_timing(steps, rounds=3, iters=2, warmup=1, clock=clock)
    assert calls == ["A", "B"] + ["A", "A", "B", "B"] + ["B", "B", "A", "A"] + ["A", "A", "B", "B"]
    assert per_round == {"A": [3.0, 3.0, 6.0], "B": [1.0, 1.0, 2.0]}
    out = bench_reference.speedups(per_round, "A")
    assert out["step_s"] == {"A": 3.0, "B": 1.0}  # medians
    assert out["speedup_per_round"] == {"B": [3.0, 3.0, 3.0]}  # paired within the round: the slow spell cancels
    assert out["speedup"] == {"B": 3.0}
    assert out["step_s_per_round"] == per_round


def test_summary_speedups_come_from_the_reference_section_alone():
    records = [{"name": name, "samples_per_s": 100.0, "step_s": 1.0, "settings": {"batch": 128}}
               for name in ("train/dnri/synth", "train/dnri/recurrent")]
    reference = {"cases": {"train/dnri/synth": {"speedup": {"fp32": 1.5, "bf16": 2.5},
                                                "ceiling": {"speedup": {"fp32": 1.9, "bf16": 4.7}}},
                           "train/dnri/recurrent": {"speedup": {"fp32": 1.7}}}}  # bf16 left out, older JSON
    out = bench.summary(records, reference)
    assert {k: v for k, v in out.items() if "over_reference" in k} == {
        "speedup_over_reference/train/dnri/synth": 1.5, "speedup_over_reference/train/dnri/synth/bf16": 2.5,
        "ceiling_over_reference/train/dnri/synth": 1.9, "ceiling_over_reference/train/dnri/synth/bf16": 4.7,
        "speedup_over_reference/train/dnri/recurrent": 1.7}
    assert not any("over_reference" in k for k in bench.summary(records))  # without --reference


@pytest.mark.skipif(not (REFERENCE_CHECKOUT / "dnri" / "models" / "dnri.py").is_file(),
                    reason=f"no checkout of cgraber/cvpr_dNRI at {REFERENCE_CHECKOUT} (set DIDER_DNRI_REFERENCE)")
@pytest.mark.parametrize("bf16", ["yes", "no"])
def test_reference_comparison_at_tiny_sizes(tmp_path, bf16):
    """The comparison at toy sizes; ``--bf16 no`` (auto's choice on a CPU without native bf16) leaves ours in
    bf16 out of the rounds and the summary."""
    out = tmp_path / "results.json"
    bench.main(["--reference", str(REFERENCE_CHECKOUT), "--reference-size", "tiny", "--reference-rounds", "2",
                "--reference-iters", "1", "--reference-threads", "1", "--only", "reference", "--out", str(out),
                "--bf16", bf16])
    doc = json.loads(out.read_text())
    variants = ("fp32", "bf16") if bf16 == "yes" else ("fp32",)
    assert doc["meta"]["bf16"] is (bf16 == "yes")
    assert doc["records"] == []  # --only reference: the comparison alone
    section = doc["reference"]
    assert "error" not in section and Path(section["checkout"]) == REFERENCE_CHECKOUT.resolve()
    assert set(section["cases"]) == set(bench.REFERENCE_CASES)
    for name, case in section["cases"].items():
        assert (case["batch"], case["steps"], case["size"], case["threads"]) == (4, 8, "tiny", 1)
        assert case["torch"] == torch.__version__ and case["rounds"] == 2
        assert set(case["step_s"]) == {"reference", *variants} and set(case["speedup"]) == set(variants)
        for variant in ("reference", *variants):
            assert len(case["step_s_per_round"][variant]) == 2 and case["step_s"][variant] > 0
        for variant in variants:
            ratios = case["speedup_per_round"][variant]
            assert ratios == [r / o for r, o in zip(case["step_s_per_round"]["reference"],
                                                    case["step_s_per_round"][variant], strict=True)]
            suffix = "" if variant == "fp32" else "/bf16"
            assert doc["summary"][f"speedup_over_reference/{name}{suffix}"] == case["speedup"][variant]
        assert (f"speedup_over_reference/{name}/bf16" in doc["summary"]) is (bf16 == "yes")
        ceiling = case["ceiling"]  # the matmul-only ceiling, from this run's step arithmetic and matmul rates
        assert set(ceiling["speedup"]) == set(variants) and ceiling["gflop_per_step"] > 0
        for variant in variants:
            step = ceiling["gflop_per_step"] / ceiling["gemm_gflop_per_s"][variant]
            assert ceiling["speedup"][variant] == pytest.approx(case["step_s"]["reference"] / step)
            suffix = "" if variant == "fp32" else "/bf16"
            assert doc["summary"][f"ceiling_over_reference/{name}{suffix}"] == ceiling["speedup"][variant]
    assert section["cases"]["train/dnri/synth"]["reference_params"]["decoder_type"] == "ref_mlp"
    assert section["cases"]["train/dnri/recurrent"]["reference_params"]["add_uniform_prior"] is False


def test_largest_agents_finds_the_exact_bound_of_a_quadratic_peak():
    """A fake step whose peak is 500 + 2 N (N - 1) MB: the largest N within 3000 MB is 35 (2880; 36: 3020)."""
    from dider.bench.memory import largest_agents

    probed = []

    def probe(n):
        probed.append(n)
        return 500.0 + 2.0 * n * (n - 1)

    found = largest_agents(probe, 3000.0, ceiling_mb=1e9, start={10: probe(10), 20: probe(20)})
    assert found["largest_agents"] == 35 and found["bound"] == "measured"
    assert found["probes"][35] <= 3000 < found["probes"][36]
    assert len(probed) <= 2 + 4  # the fitted line aims at the bound: a few probes, not a scan


def test_largest_agents_never_runs_a_probe_predicted_over_the_machine():
    """With the machine's ceiling at 2000 MB, N = 36 (predicted 3020 MB) must not run: the bound is predicted."""
    from dider.bench.memory import largest_agents

    def probe(n):
        assert 500.0 + 2.0 * n * (n - 1) <= 2000.0, f"N = {n} was run"
        return 500.0 + 2.0 * n * (n - 1)

    found = largest_agents(probe, 3000.0, ceiling_mb=2000.0, start={10: probe(10)})
    assert found["largest_agents"] == 27  # 500 + 2 * 27 * 26 = 1904; N = 28: 2012 > the ceiling, not run
    assert found["bound"] == "predicted" and 28 in found["predicted"] and 28 not in found["probes"]
    none = largest_agents(probe, 100.0, ceiling_mb=2000.0, start={10: probe(10)})
    assert none["largest_agents"] is None  # even the smallest measured N is over the budget


@pytest.mark.slow  # trains the documented job; make test-all
def test_time_to_result_runs_the_documented_job_and_reads_its_metrics(tmp_path, capsys):
    """``--only result/demo --quick``: the demo's job at toy sizes, as its own process; the record has the wall
    time and the model's edge recall and forecast error read back from the run's metrics.json."""
    from dider.bench.result import RESULT_METRICS

    out = tmp_path / "bench.json"
    bench.main(["--only", "result/demo", "--quick", "--out", str(out)])
    doc = json.loads(out.read_text())
    assert doc["meta"]["command"] == f"python -m dider.bench --only result/demo --quick --out {out}"  # remade by it
    (record,) = doc["records"]
    assert record["name"] == "result/demo" and "error" not in record, record.get("error")
    assert record["wall_s"] > 0 and record["runs"] == 1 and record["failed_runs"] == 0 and record["complete"]
    assert record["command"] == "python -m dider.run experiment=demo" and record["quick"]
    (label, values), = record["models"].items()
    assert label == "dider"
    assert set(RESULT_METRICS) <= set(values) and 0 <= values["test/edge_acc/posterior/none"] <= 1
    assert "result/demo" in capsys.readouterr().out


def test_result_cases_run_only_when_named(monkeypatch, tmp_path):
    """A plain ``make bench`` must not start whole training jobs."""
    monkeypatch.setattr(bench, "cases", lambda: [bench.Case("result/demo", [], 0, 0, 0, kind="result")])
    monkeypatch.setattr(bench, "time_to_result", lambda *a, **k: pytest.fail("a result case ran unnamed"))
    assert bench.main(["--out", str(tmp_path / "b.json")]) == []


def test_profile_writes_the_op_table_of_one_training_step(monkeypatch, tmp_path, capsys):
    tiny = bench.REFERENCE_SIZES["tiny"]
    case = bench.Case("train/dnri/tiny", ["model=dnri", *tiny["overrides"]], tiny["batch"], 3, tiny["steps"], warmup=1)
    monkeypatch.setattr(bench, "cases", lambda: [case, bench.Case("rollout/x", [], 1, 3, 8, kind="rollout")])
    assert bench.main(["--profile", "train/dnri/tiny", "--out", str(tmp_path / "b.json")]) == []
    table = (tmp_path / "profile_train_dnri_tiny.txt").read_text()
    assert "aten::addmm" in table and "Self CPU" in table  # the edge MLPs' matmuls, with self times
    assert table in capsys.readouterr().out
    assert not (tmp_path / "b.json").exists()  # nothing timed
    with pytest.raises(SystemExit):
        bench.main(["--profile", "rollout/x", "--out", str(tmp_path / "b.json")])
    assert "'rollout/x': not a training case; one of train/dnri/tiny" in capsys.readouterr().err
