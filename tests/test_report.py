"""The experiment sweeps compose, and `dider.analysis.report` aggregates a real sweep faithfully."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import dider.conf
import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.types import RunMode
from omegaconf import OmegaConf

from dider.analysis import report, report_table

EXPERIMENTS = ["synth_table", "synth_cpu_table", "bball_table", "ind50_table", "ind200_table", "edge_ablation"]


@pytest.fixture(scope="module")
def sweep(tmp_path_factory: pytest.TempPathFactory, cache_dir: Path) -> Path:
    """A real 2 models x 2 seeds multirun (smoke-sized: tens of seconds)."""
    out = tmp_path_factory.mktemp("sweep")
    cmd = [sys.executable, "-m", "dider.run", "-m", "experiment=smoke", "model=dnri,dider", "seed=1,2",
           f"hydra.sweep.dir={out}", f"data.cache_dir={cache_dir}", "logger=csv", "trainer.enable_progress_bar=false",
           "data.num_train=32", "data.num_val=8", "data.num_test=8", "data.loader.eval_batch_size=8"]
    proc = subprocess.run(cmd, env={**os.environ, "HYDRA_FULL_ERROR": "1"}, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def job_dirs(sweep: Path) -> dict[tuple[str, int], Path]:
    """(model, seed) -> job folder (job folders are named by all their overrides, sizes included)."""
    records = {p.parent: json.loads(p.read_text()) for p in sweep.glob("*/metrics.json")}
    return {(r["model"], r["seed"]): d for d, r in records.items()}


def read_csv(path: Path) -> dict[str, dict[str, str]]:
    with path.open() as f:
        return {row["model"]: row for row in csv.DictReader(f)}


def test_report_matches_jobs(sweep: Path, tmp_path: Path):
    summary = report.main([str(sweep), "--out", str(tmp_path)])
    assert not summary.failed and not summary.missing and summary.expected == 4
    rows = read_csv(tmp_path / "report.csv")
    assert list(rows) == ["dnri", "dider"]  # the sweep's order
    for model, row in rows.items():
        jobs = [json.loads((job_dirs(sweep)[model, seed] / "metrics.json").read_text())["metrics"] for seed in (1, 2)]
        assert len(jobs) == 2 and row["n"] == "2" and row["seeds"] == "1;2"
        for metric in ("test/mse/h01", "test/mse/h15", "test/mse/h25", "test/edge_acc/posterior/interaction"):
            values = np.array([m[metric] for m in jobs])
            assert float(row[f"{metric}_mean"]) == pytest.approx(values.mean(), rel=1e-12)
            assert float(row[f"{metric}_std"]) == pytest.approx(values.std(ddof=1), rel=1e-12)
    md = (tmp_path / "report.md").read_text()
    h01 = np.array([json.loads((job_dirs(sweep)["dnri", s] / "metrics.json").read_text())["metrics"]["test/mse/h01"]
                    for s in (1, 2)])
    table = md.split("## Forecast MSE (normalised units)")[1].split("\n## ")[0].splitlines()
    header, row = table[2].split(" | "), next(r for r in table if r.startswith("| dnri |")).split(" | ")
    power = re.fullmatch(r"h01(?: \(×1e(-?\d+)\))?", header[2]).group(1)  # the column's power of ten
    mean, std = (float(v.strip("*†")) * 10.0 ** int(power or 0) for v in row[2].split(" ± "))
    decimals = len(row[2].split(" ± ")[1].split(".")[1])  # the same decimals for mean and std
    unit = 10.0 ** (int(power or 0) - decimals)
    assert abs(mean - h01.mean()) <= unit / 2 + 1e-15 and abs(std - h01.std(ddof=1)) <= unit / 2 + 1e-15
    # the model's own slots and the held types' switches are separate tables
    slots = md.split("## Duration slots: the model's own cut")[1].split("\n## ")[0]
    assert "segments/steps_per_segment" in slots and "switches_per_100" not in slots
    assert "segments_per_edge" in md.split("\n## Segments")[1].split("\n## ")[0]
    assert (tmp_path / "horizons.png").stat().st_size > 0
    assert sorted(p.parent.name for p in tmp_path.glob("timelines/*/timeline_00.png")) == ["dider", "dnri"]
    assert md.rstrip().endswith("## Failed, missing or ignored jobs\n\n(failed: a job folder without a readable "
                                "metrics.json, with why, or one still running; missing: swept values that no job "
                                "folder holds; ignored: a finished run whose overrides are not a job of this sweep, "
                                "e.g. copied in, left out of the tables)\n\nnone")


def test_runs_csv_has_one_row_per_job(sweep: Path, tmp_path: Path):
    report.main([str(sweep), "--out", str(tmp_path)])
    with (tmp_path / "runs.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert sorted((r["model"], int(r["seed"])) for r in rows) == sorted(job_dirs(sweep))
    for r in rows:
        record = json.loads((sweep / r["job"] / "metrics.json").read_text())
        assert float(r["test/mse/h15"]) == record["metrics"]["test/mse/h15"]
        assert r["data.num_train"] == "32"  # a setting of the sweep's command line


@pytest.mark.parametrize("df, expected", [(1, 12.706), (3, 3.182), (30, 2.042), (31, 2.0395), (60, 2.0003),
                                          (1000, 1.9623)])
def test_t_quantile(df: int, expected: float):
    """The 95% band uses Student's t (3.18 for 4 seeds, not 1.96); values from statistical tables."""
    assert report_table.t975(df) == pytest.approx(expected, abs=6e-4)
    assert np.isnan(report_table.t975(0))


def test_failed_and_missing_jobs_listed(sweep: Path, tmp_path: Path):
    broken = tmp_path / "sweep"
    shutil.copytree(sweep, broken, ignore=shutil.ignore_patterns("checkpoints", "*.png", "csv"))
    crashed, killed = (job_dirs(sweep)[key].name for key in (("dider", 2), ("dnri", 2)))
    (broken / crashed / "metrics.json").unlink()  # crashed: .hydra/ but no metrics.json
    shutil.rmtree(broken / killed)  # never launched (a sweep killed part-way)
    summary = report.main([str(broken)])
    assert summary.failed == [f"{crashed} (no metrics.json)"]
    assert summary.missing == ["model=dnri,seed=2"]  # the swept values of the combination no folder holds
    assert [len(g.jobs) for g in summary.groups] == [1, 1]
    md = (broken / "report.md").read_text()
    assert f"- failed: `{crashed} (no metrics.json)`" in md and "- missing: `model=dnri,seed=2`" in md
    assert "2 finished jobs, 1 failed, 1 missing (the sweep expects 4)" in md


def fake_sweep(root: Path, params: dict[str, str], jobs: list[tuple[str, int, int]]) -> Path:
    """A sweep folder with multirun.yaml and hand-written metrics.json records: (model, num_edges, seed) jobs."""
    hydra_cfg = {"sweeper": {"_target_": "hydra._internal.core_plugins.basic_sweeper.BasicSweeper", "params": params},
                 "overrides": {"task": ["experiment=x"]},
                 "job": {"config": {"override_dirname": {"exclude_keys": ["experiment"]}}}}
    OmegaConf.save(OmegaConf.create({"hydra": hydra_cfg}), root / "multirun.yaml")
    for model, e, seed in jobs:
        job = root / f"model={model},e={e},seed={seed}"
        overrides = ["experiment=x", f"model={model}", f"seed={seed}"]
        overrides += [f"model.num_edges={e}"] if "model.num_edges" in params else []
        (job / ".hydra").mkdir(parents=True)
        OmegaConf.save(OmegaConf.create(overrides), job / ".hydra" / "overrides.yaml")
        metrics = {"test/mse/h01": 1e-5 * (e + seed), "test/mse/h20": 1e-3 * (7 - e) * seed}
        record = {"metrics": metrics, "overrides": overrides, "seed": seed, "model": model,
                  "config": {"model": {"num_edges": e}}}
        (job / "metrics.json").write_text(json.dumps(record))
    return root


def test_a_run_copied_into_a_sweep_is_left_out_and_named(tmp_path: Path):
    jobs = [("dnri", 2, seed) for seed in (1, 2)]
    (tmp_path / "sweep").mkdir()
    (tmp_path / "other").mkdir()
    sweep = fake_sweep(tmp_path / "sweep", {"model": "dnri", "seed": "1,2"}, jobs)
    other = fake_sweep(tmp_path / "other", {"model": "dnri", "seed": "7"}, [("dnri", 2, 7)])
    shutil.copytree(other / "model=dnri,e=2,seed=7", sweep / "copied")
    summary = report.main([str(sweep), "--out", str(tmp_path / "out")])
    assert [len(g.jobs) for g in summary.groups] == [2] and summary.missing == [] and summary.failed == []
    assert summary.ignored == ["copied (its overrides are not a job of this sweep)"]
    md = (tmp_path / "out" / "report.md").read_text()
    assert "- ignored: `copied (its overrides are not a job of this sweep)`" in md


def test_edge_ablation_plot(tmp_path: Path):
    """num_edges swept: one row per num_edges and the MSE-vs-num_edges plot (fake job records)."""
    jobs = [("dider", e, seed) for e in (2, 4) for seed in (1, 2)]
    sweep = fake_sweep(tmp_path, {"model": "dider", "model.num_edges": "2,4", "seed": "1,2"}, jobs)
    summary = report.main([str(sweep), "--out", str(tmp_path / "out")])
    assert [g.key for g in summary.groups] == [{"model": "dider", "num_edges": 2}, {"model": "dider", "num_edges": 4}]
    assert summary.stats.loc[1, "test/mse/h20"][["mean", "std", "n"]].tolist() == pytest.approx(
        [4.5e-3, np.std([3e-3, 6e-3], ddof=1), 2])
    assert (tmp_path / "out" / "edge_ablation.png").stat().st_size > 0
    md = (tmp_path / "out" / "report.md").read_text()
    # h01: 3e-5, 4e-5 against 5e-5, 6e-5 on seeds 1, 2: lower on each seed by the same 2e-5, so the paired
    # interval is a point below 0; h20: 5e-3, 1e-2 against 3e-3, 6e-3: differences -2e-3, -4e-3 over 2 seeds,
    # mean -3e-3 +- 12.706 * 1e-3 reaches 0
    assert "mse/h01: lowest mean MSE at num_edges=2 (paired over 2 seeds, 95%)" in md
    tex = (tmp_path / "out" / "report.tex").read_text()
    # one power of ten and one number of decimals per column (3 significant digits of its largest mean); the
    # best mean in bold, with a dagger only where the paired comparison supports it (h01, not h20)
    assert (r"model & num\_edges & $n$ & mse/h01 ($\times 10^{-5}$) & mse/h20 ($\times 10^{-3}$) \\" in tex
            and r"\toprule" in tex)
    assert r"dider & 2 & 2 & \textbf{3.50}$^\dagger$ $\pm$ 0.71 & 7.50 $\pm$ 3.54 \\" in tex
    assert r"dider & 4 & 2 & 5.50 $\pm$ 0.71 & \textbf{4.50} $\pm$ 2.12 \\" in tex
    assert "| dider | 2 | 2 | **3.50**† ± 0.71 | 7.50 ± 3.54 |" in md
    assert "| model | num_edges | n | h01 (×1e-5) | h20 (×1e-3) |" in md
    assert ("mse/h20: lowest mean MSE at num_edges=4, not established: paired over 2 seed(s), the 95% interval of "
            "its difference to num_edges=2 reaches 0") in md


def test_num_edges_per_model_no_ablation(tmp_path: Path):
    """inD tables: num_edges differs between models (DNRI 4, DIDER 6) but is not swept: no ablation plot."""
    jobs = [(m, e, seed) for m, e in (("dnri", 4), ("dider", 6)) for seed in (1, 2)]
    summary = report.main([str(fake_sweep(tmp_path, {"model": "dnri,dider", "seed": "1,2"}, jobs))])
    assert [g.key for g in summary.groups] == [{"model": "dnri", "num_edges": 4}, {"model": "dider", "num_edges": 6}]
    assert not summary.missing and not (tmp_path / "edge_ablation.png").exists()
    assert (tmp_path / "horizons.png").exists()


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_experiment_sweeps_compose(experiment: str):
    path = Path(dider.conf.__file__).parent / "experiment" / f"{experiment}.yaml"
    assert path.read_text().splitlines()[0] == "# @package _global_"  # otherwise Hydra nests it: no sweep
    GlobalHydra.instance().clear()
    with initialize_config_module(version_base="1.3", config_module="dider.conf"):
        cfg = compose("config", overrides=[f"experiment={experiment}"], return_hydra_config=True)
        assert cfg.hydra.mode == RunMode.MULTIRUN
        params = cfg.hydra.sweeper.params
        assert "seed" in params and ("model" in params or "model.num_edges" in params)
        assert experiment in cfg.hydra.sweep.dir
        if experiment.startswith("ind"):  # DNRI 4 edge types, the DIDER variants 6
            edges = {m: compose("config", overrides=[f"experiment={experiment}", f"model={m}"]).model.num_edges
                     for m in ("dnri", "dider_skid", "dider")}
            assert edges == {"dnri": 4, "dider_skid": 6, "dider": 6}
            net = cfg.model.net
            assert net.decoder._target_.endswith("RecurrentDecoder") and net.objective.sparsity is None
    GlobalHydra.instance().clear()


def test_horizon_bands_stop_a_decade_below_the_mean(tmp_path: Path, monkeypatch):
    """Two seeds far apart give 95% bands reaching below 0; on the log axis each band's lower edge stops at a
    tenth of the mean instead of spanning decades. h01: 3e-5, 7e-5 (mean 5e-5); h20: 5e-3, 2.5e-2 (mean 1.5e-2);
    half-widths 12.706 * std / sqrt(2) exceed both means."""
    (tmp_path / "sweep").mkdir()
    sweep = fake_sweep(tmp_path / "sweep", {"model": "dnri", "seed": "1,5"}, [("dnri", 2, 1), ("dnri", 2, 5)])
    figures = []
    monkeypatch.setattr(report, "_save", lambda fig, path: figures.append(fig))
    assert report.horizons_figure(report.summarise(sweep), tmp_path / "h.png")
    (band,) = figures[0].axes[0].collections
    ys = band.get_paths()[0].vertices[:, 1]
    assert ys.min() == pytest.approx(5e-6) and np.isclose(ys, 1.5e-3).any()
    fig = figures[0]  # the title lies inside the figure, not cut at its edges
    box, title = fig.bbox, fig.axes[0].title.get_window_extent(fig.canvas.get_renderer())
    assert box.x0 <= title.x0 and title.x1 <= box.x1 and title.y1 <= box.y1


@pytest.mark.parametrize("means, exponent, decimals, cells", [
    ([0.912, 1.23], 0, 2, ["0.91", "1.23"]),  # 3 significant digits of the largest: 2 decimals for all
    ([5.1, 12.345], 0, 1, ["5.1", "12.3"]),
    ([3.5e-5, 5.5e-5], -5, 2, ["3.50", "5.50"]),  # below 0.01: a power of ten in the header
    ([123456.0, 20000.0], 5, 2, ["1.23", "0.20"]),
    ([float("nan"), 0.5], 0, 3, ["–", "0.500"])])
def test_column_format(means: list[float], exponent: int, decimals: int, cells: list[str]):
    fmt = report_table.ColumnFormat.of(means)
    assert (fmt.exponent, fmt.decimals) == (exponent, decimals)
    assert [fmt.cell(m)[0] for m in means] == cells
    assert fmt.cell(means[1], 0.0123 * 10.0**exponent)[1] == f"{0.0123:.{decimals}f}"


def test_ratios_to_dnri_are_paired_by_seed(tmp_path: Path):
    """ADE over DNRI's on the same seed: dider seed 1 (2.0 m) over dnri seed 1 (4.0 m), seed 2 (3.0 / 2.0)."""
    jobs = [(m, 2, seed) for m in ("dnri", "dider") for seed in (1, 2)]
    sweep = fake_sweep(tmp_path, {"model": "dnri,dider", "seed": "1,2"}, jobs)
    ade = {("dnri", 1): 4.0, ("dnri", 2): 2.0, ("dider", 1): 2.0, ("dider", 2): 3.0}
    for f in sweep.glob("*/metrics.json"):
        record = json.loads(f.read_text())
        record["metrics"]["test/ade/h20"] = ade[record["model"], record["seed"]]
        f.write_text(json.dumps(record))
    summary = report.main([str(sweep), "--out", str(tmp_path / "out")])
    dider = next(i for i, g in enumerate(summary.groups) if g.key["model"] == "dider")
    assert summary.stats.loc[dider, "test/ade_vs_dnri/h20"][["mean", "std", "n"]].tolist() == pytest.approx(
        [1.0, np.std([0.5, 1.5], ddof=1), 2])
    assert summary.stats[("test/ade_vs_dnri/h20", "ci95")][1] == pytest.approx(12.706 * np.std([0.5, 1.5], ddof=1)
                                                                                / np.sqrt(2))
    assert "## Forecast against DNRI" in (tmp_path / "out" / "report.md").read_text()
    assert r"ade\_vs\_dnri/h20" in (tmp_path / "out" / "report.tex").read_text()


def test_paired_support_higher_is_better():
    """Edge recall: group 0 higher on each of 3 seeds by 0.1, 0.2, 0.15: mean 0.15, std 0.05, half-width
    4.303 * 0.05 / sqrt(3) = 0.124 < 0.15: supported; against 2 seeds (12.706 * 0.0707 / sqrt(2) = 0.635): not."""
    metric = "test/edge_acc/posterior/interaction"
    frame = pd.DataFrame({"group": [0, 0, 0, 1, 1, 1], "seed": [1, 2, 3] * 2,
                          metric: [0.9, 0.8, 0.85, 0.8, 0.6, 0.7]})
    assert report_table.paired_support(frame, 0, metric) == (True, 3, None)
    assert report_table.paired_support(frame[frame.seed < 3], 0, metric) == (False, 2, 1)
    assert report_table.direction(metric) == 1 and report_table.direction("test/ade_vs_cv/h20") == -1
    assert report_table.direction("test/type1/distance") == 0


def test_paired_support_needs_seeds_it_can_pair():
    """No seeds, one shared seed, or a seed run twice: nothing is established, whatever the means."""
    metric = "test/ade/h20"
    frame = pd.DataFrame({"group": [0, 0, 1, 1], "seed": [None, None, None, None], metric: [1.0, 1.1, 2.0, 2.1]})
    assert report_table.paired_support(frame, 0, metric) == (False, 0, 1)
    frame["seed"] = [1, 2, 3, 4]  # no seed in common
    assert report_table.paired_support(frame, 0, metric) == (False, 0, 1)
    frame["seed"] = [1, 1, 1, 2]  # group 0 ran seed 1 twice
    assert report_table.paired_support(frame, 0, metric) == (False, 0, 1)
    frame["seed"] = [1, 2, 1, 2]
    assert report_table.paired_support(frame, 0, metric) == (True, 2, None)  # differences -1, -1: a point below 0


def test_ratios_to_dnri_pair_num_edges_when_dnri_ran_several(tmp_path: Path):
    """DNRI with 2 and 4 edge types: each job is divided by DNRI's with its own num_edges; a sweep of DNRI
    alone gets no ratio columns."""
    jobs = [(m, e, 1) for m in ("dnri", "dider") for e in (2, 4)]
    sweep = fake_sweep(tmp_path, {"model": "dnri,dider", "model.num_edges": "2,4", "seed": "1"}, jobs)
    groups = report.group_jobs(report.collect(sweep)[0], sweep)
    assert report_table.add_ratios(groups) == []  # no ADE in these records
    for g in groups:
        for j in g.jobs:
            j["metrics"]["test/ade/h20"] = {"dnri": 2.0, "dider": 3.0}[g.key["model"]] * g.key["num_edges"]
    assert report_table.add_ratios(groups) == ["test/ade_vs_dnri/h20"]
    assert {(g.key["model"], g.key["num_edges"]): g.jobs[0]["metrics"]["test/ade_vs_dnri/h20"] for g in groups} == {
        ("dnri", 2): 1.0, ("dnri", 4): 1.0, ("dider", 2): 1.5, ("dider", 4): 1.5}
    only = [g for g in groups if g.key["model"] == "dnri"]
    assert report_table.add_ratios(only) == []


def test_broken_running_and_evaluated_jobs(tmp_path: Path, caplog):
    """A job whose metrics.json is not an object and one still running are listed with why, never read as results; a
    job's own evaluation (eval/<name>/ inside it) is not another job of the sweep; two jobs of the same settings are
    both kept, with a warning."""
    import os
    import socket

    jobs = [("dnri", 2, seed) for seed in (1, 2, 3)]
    sweep = fake_sweep(tmp_path, {"model": "dnri", "seed": "1,2,3"}, jobs)
    (sweep / "model=dnri,e=2,seed=2" / "metrics.json").write_text("[]")
    running = sweep / "model=dnri,e=2,seed=3"
    (running / "metrics.json").unlink()
    (running / ".dider.lock").write_text(json.dumps({"pid": os.getppid(), "host": socket.gethostname()}))
    evaluated = sweep / "model=dnri,e=2,seed=1" / "eval" / "synth"
    shutil.copytree(sweep / "model=dnri,e=2,seed=1", evaluated)
    shutil.copytree(sweep / "model=dnri,e=2,seed=1", sweep / "twin", ignore=shutil.ignore_patterns("eval"))
    with caplog.at_level("WARNING", logger="dider.analysis.report"):
        summary = report.main([str(sweep), "--out", str(tmp_path / "out")])
    assert len(summary.failed) == 2
    assert summary.failed[0].startswith("model=dnri,e=2,seed=2 (") and "is not a run's record" in summary.failed[0]
    assert summary.failed[1].startswith(f"model=dnri,e=2,seed=3 (running (pid {os.getppid()} ")
    assert [len(g.jobs) for g in summary.groups] == [2]  # seed 1 and its twin; not the evaluation
    assert "ran the same settings: both are kept" in caplog.text and "twin" in caplog.text


def test_the_reference_of_a_ratio_is_not_its_best_row_and_a_wide_table_is_split(tmp_path: Path):
    """DNRI's own row of ADE over DNRI's is 1 on every seed: no rival. DIDER's ratios are 0.75 and 1.5 (mean
    1.125): with DNRI's row left out no other row is there to beat, so nothing in that column is bold; nor where
    the two rows tie (MSE). Ten value columns go into two tabulars of five."""
    jobs = [(m, 2, seed) for m in ("dnri", "dider") for seed in (1, 2)]
    sweep = fake_sweep(tmp_path, {"model": "dnri,dider", "seed": "1,2"}, jobs)
    ade = {("dnri", 1): 4.0, ("dnri", 2): 2.0, ("dider", 1): 3.0, ("dider", 2): 3.0}
    for f in sweep.glob("*/metrics.json"):
        record = json.loads(f.read_text())
        for h in (1, 5, 10, 20):
            record["metrics"][f"test/ade/h{h:02d}"] = ade[record["model"], record["seed"]] * h
        f.write_text(json.dumps(record))
    report.main([str(sweep), "--out", str(tmp_path / "out")])
    tex = (tmp_path / "out" / "report.tex").read_text()
    assert tex.count(r"\begin{tabular}") == 2 and tex.count(r"\begin{table}") == 1  # 4 ratios, 4 ADEs, 2 MSEs
    assert "mse/h01" in tex.split(r"\medskip")[1] and r"\textbf{3.50}" not in tex
    ratios = [line for line in tex.splitlines() if "ade\\_vs\\_dnri/h01" in line]
    assert ratios, tex
    rows = tex.split(ratios[0], 1)[1].split(r"\bottomrule", 1)[0]
    assert r"\textbf" not in rows and "1.00 $\\pm$ 0.00" in rows.replace("1.000", "1.00")
    md = (tmp_path / "out" / "report.md").read_text()
    assert "**1.00" not in md
