"""Records of sweeps (``python -m dider.analysis.record``): grouping by model and seed, summaries, paired
differences."""

import json
import math
from pathlib import Path

import pytest

from dider.analysis.record import main


def fake_job(root, name, model, seed, h15, overrides=()):
    folder = root / name
    folder.mkdir(parents=True)
    record = {"seed": seed, "model": model, "overrides": [f"model={model}", f"seed={seed}", *overrides],
              "config": {"model": {"name": model}}, "metrics": {"test/mse/h15": h15, "test/mse/h25": 2 * h15},
              "provenance": {"wall_s": 10.0 * seed, "device": "cpu", "git_commit": "abc", "torch": "2"}}
    (folder / "metrics.json").write_text(json.dumps(record))


def test_record_summarises_and_pairs_by_seed(tmp_path):
    sweep = tmp_path / "sweep"
    for seed, (a, b) in {1: (1.0, 2.0), 2: (3.0, 2.0), 3: (2.0, 5.0)}.items():
        fake_job(sweep, f"dider{seed}", "dider", seed, a)
        fake_job(sweep, f"dnri{seed}", "dnri", seed, b)
    fake_job(sweep, "dnri4", "dnri", 4, 100.0)  # a seed the other model lacks: in its summary, not in the pairs
    out = tmp_path / "rec.json"
    record = main([str(sweep), "--out", str(out), "--baseline", "dnri", "--command", "cmd", "--metric", "test/mse/h15"])
    assert json.loads(out.read_text()) == record and record["command"] == "cmd"
    h15 = record["models"]["dider"]["test/mse/h15"]
    assert h15["n"] == 3 and h15["mean"] == pytest.approx(2.0) and h15["std"] == pytest.approx(1.0)
    diff = h15["vs_dnri"]  # differences -1, 1, -3: mean -1, sample std 2, standard error 2 / sqrt(3)
    assert diff["n"] == 3 and diff["mean"] == pytest.approx(-1.0) and diff["se"] == pytest.approx(2 / math.sqrt(3))
    assert diff["below"] == 2 and diff["ratio_of_means"] == pytest.approx(6 / 9)
    baseline = record["models"]["dnri"]["test/mse/h15"]
    assert baseline["n"] == 4 and "vs_dnri" not in baseline
    job = next(j for j in record["jobs"] if j["folder"].endswith("dider2"))  # each job's cost and code, as it ran
    assert job["provenance"] == {"wall_s": 20.0, "device": "cpu", "git_commit": "abc"}


def test_jobs_that_differ_by_an_override_are_grouped_apart_unless_asked(tmp_path):
    fake_job(tmp_path / "a", "j1", "dider", 1, 1.0, ["model.net.objective.prior_fit.weight=2"])
    fake_job(tmp_path / "b", "j2", "dider", 2, 3.0)
    out = tmp_path / "rec.json"
    assert sorted(main([str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out)])["models"]) == [
        "dider", "dider [model.net.objective.prior_fit.weight=2]"]
    assert list(main([str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(out), "--by-name"])["models"]) == ["dider"]
    with pytest.raises(FileNotFoundError, match="no such run or sweep folder"):
        main([str(tmp_path / "nothing"), "--out", str(out)])


def test_two_spellings_of_one_configuration_are_recorded_as_one_model(tmp_path):
    fake_job(tmp_path / "a", "j1", "dider", 1, 1.0, ["+model.net.objective.w=2"])
    fake_job(tmp_path / "b", "j2", "dider", 2, 3.0, ["model/net/objective=w2"])
    fake_job(tmp_path / "c", "j3", "dnri", 1, 5.0)
    out, paths = tmp_path / "rec.json", [str(tmp_path / d) for d in "abc"]
    record = main([*paths, "--out", str(out), "--rename", "dider [+model.net.objective.w=2]=w2",
                   "--rename", "dider [model/net/objective=w2]=w2"])
    assert sorted(record["models"]) == ["dnri", "w2"] and record["models"]["w2"]["test/mse/h15"]["mean"] == 2.0
    assert sorted(j["model"] for j in record["jobs"]) == ["dnri", "w2", "w2"]
    with pytest.raises(ValueError, match="no job is labelled 'dider'"):
        main([*paths, "--out", str(out), "--rename", "dider=w2"])


def test_training_metrics_come_from_the_csv_log(tmp_path):
    """train/ and val/ metrics are read from csv/metrics.csv: the last row that holds a value."""
    fake_job(tmp_path, "j1", "dider", 1, 1.0)
    (tmp_path / "j1" / "csv").mkdir()
    (tmp_path / "j1" / "csv" / "metrics.csv").write_text(
        "epoch,train/segments/steps_per_segment,val/x\n0,3.5,\n0,,7\n1,4.5,\n1,,\n")
    record = main([str(tmp_path), "--out", str(tmp_path / "r.json"), "--metric", "train/segments/steps_per_segment",
                   "--metric", "val/x", "--metric", "test/mse/h15"])
    assert record["jobs"][0]["metrics"] == {"test/mse/h15": 1.0, "train/segments/steps_per_segment": 4.5,
                                            "val/x": 7.0}


def test_curves_keep_a_metric_over_the_epochs(tmp_path):
    fake_job(tmp_path, "j1", "dnri", 1, 1.0)
    (tmp_path / "j1" / "csv").mkdir()
    (tmp_path / "j1" / "csv" / "metrics.csv").write_text(
        "epoch,step,val/mse/h01,train/loss\n0,9,0.5,\n0,9,,3\n1,19,0.25,\n")
    record = main([str(tmp_path), "--out", str(tmp_path / "r.json"), "--curve", "val/mse/h01", "--curve", "x"])
    assert record["jobs"][0]["curves"] == {"val/mse/h01": [[0, 9, 0.5], [1, 19, 0.25]]}


def test_broken_failed_and_running_jobs_are_named_and_left_out(tmp_path, caplog):
    """A metrics.json that is not an object, one cut off mid-write, a failed job and a running one (its lock held by a
    live process): each is named with its reason in a warning and in the record's ``unfinished``, never read as a
    result; the finished jobs are recorded."""
    import os
    import socket

    sweep = tmp_path / "sweep"
    fake_job(sweep, "ok", "dnri", 1, 1.0)
    for name, text in (("list", "[1, 2]"), ("half", '{"metrics": {"test/mse/h15": 0.')):
        (sweep / name).mkdir()
        (sweep / name / "metrics.json").write_text(text)
    (sweep / "failed").mkdir()
    (sweep / "failed" / "failed.json").write_text(json.dumps({"status": "failed", "error": "OSError('disk')"}))
    (sweep / "running" / ".hydra").mkdir(parents=True)
    (sweep / "running" / ".dider.lock").write_text(json.dumps({"pid": os.getppid(), "host": socket.gethostname()}))
    with caplog.at_level("WARNING", logger="dider.analysis.record"):
        record = main([str(sweep), "--out", str(tmp_path / "r.json")])
    assert [j["folder"] for j in record["jobs"]] == [str(sweep / "ok")]
    states = {Path(u["folder"]).name: u["state"] for u in record["unfinished"]}
    assert states["list"].startswith("failed: ") and "not a run's record" in states["list"]
    assert "is not JSON (half-written?)" in states["half"]
    assert "failed.json says OSError('disk')" in states["failed"]
    assert states["running"].startswith(f"running (pid {os.getppid()}")
    for name in states:
        assert str(sweep / name) in caplog.text
    # only unfinished jobs: refused by name, not a crash on an empty set of overrides
    with pytest.raises(FileNotFoundError, match=r"no finished job \(1 running or failed\)"):
        main([str(sweep / "failed"), "--out", str(tmp_path / "none.json")])


def test_two_jobs_of_one_model_and_seed_are_refused(tmp_path):
    fake_job(tmp_path / "a", "j1", "dider", 1, 1.0)
    fake_job(tmp_path / "b", "j1", "dider", 1, 3.0)
    with pytest.raises(ValueError, match=r"two jobs of model 'dider' with seed 1: .*a/j1 and .*b/j1"):
        main([str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "r.json")])


def test_a_baseline_with_none_of_a_quantity_pairs_without_a_ratio():
    """DNRI has no boundaries of its own: the differences pair as usual, the ratio of means is NaN, not an error."""
    from dider.analysis.record import paired

    diff = paired({1: 0.5, 2: 0.7}, {1: 0.0, 2: 0.0})
    assert diff["mean"] == pytest.approx(0.6) and diff["below"] == 0 and math.isnan(diff["ratio_of_means"])


def test_a_baseline_can_come_from_a_committed_record(tmp_path):
    """--jobs-from RECORD:MODEL pairs new jobs against a model's jobs as an earlier record holds them (the run
    folders gone): differences 1 - 2 and 3 - 5 by seed."""
    for seed, b in {1: 2.0, 2: 5.0}.items():
        fake_job(tmp_path / "old", f"dnri{seed}", "dnri", seed, b)
    old = tmp_path / "old.json"
    main([str(tmp_path / "old"), "--out", str(old)])
    for seed, a in {1: 1.0, 2: 3.0}.items():
        fake_job(tmp_path / "new", f"gate{seed}", "gate", seed, a)
    record = main([str(tmp_path / "new"), "--out", str(tmp_path / "rec.json"), "--baseline", "dnri",
                   "--jobs-from", f"{old}:dnri", "--metric", "test/mse/h15"])
    diff = record["models"]["gate"]["test/mse/h15"]["vs_dnri"]
    assert diff["n"] == 2 and diff["mean"] == pytest.approx(-1.5) and diff["se"] == pytest.approx(0.5)
    borrowed = [j for j in record["jobs"] if j["model"] == "dnri"]
    assert len(borrowed) == 2 and {j["recorded_in"] for j in borrowed} == {str(old)}
    assert all(set(j["metrics"]) == {"test/mse/h15"} for j in borrowed)
    with pytest.raises(ValueError, match="records no job of model 'nri'.*dnri"):
        main(["--out", str(tmp_path / "x.json"), "--jobs-from", f"{old}:nri"])


def test_a_nan_metric_is_said_and_an_unknown_baseline_refused(tmp_path, caplog):
    sweep = tmp_path / "sweep"
    fake_job(sweep, "a1", "dider", 1, 1.0)
    fake_job(sweep, "a2", "dider", 2, math.nan)  # no agent reached the horizon in that job
    with caplog.at_level("WARNING", logger="dider.analysis.record"):
        record = main([str(sweep), "--out", str(tmp_path / "r.json"), "--metric", "test/mse/h15"])
    assert record["models"]["dider"]["test/mse/h15"]["n"] == 1
    assert f"{sweep / 'a2'}: test/mse/h15 is NaN (no data); left out of model dider's mean" in caplog.text
    with pytest.raises(ValueError, match=r"--baseline nope: no job of that model \(models: \['dider'\]\)"):
        main([str(sweep), "--out", str(tmp_path / "r2.json"), "--baseline", "nope"])
