"""Faults and odd inputs as users meet them, one row each: prediction, the Python API, run folders, large
scenes. A command-line row runs ``python -m dider.run`` and checks its exit status, what it prints and what
it leaves behind; an API row calls a :class:`dider.trained.TrainedModel` method."""

from __future__ import annotations

import hashlib
import json
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

import dider
from helpers.fixtures import write_ind_root, write_trajectories

TINY_RUN = ["experiment=smoke", "data=trajectories", "data.num_val=4", "protocol.horizons=[1,5]",
            "data.source.frame_rate=10",
            "trainer.enable_progress_bar=false", "logger=none", "callbacks.timelines.num_clips=0", "seed=1"]


def dider_run(*args: str, cwd: Path, timeout: int = 300, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dider.run", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=timeout, **kw)


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A one-epoch DIDER run on 3-agent npz clips of 16 frames at 10 Hz."""
    root = tmp_path_factory.mktemp("trained")
    write_trajectories(root / "train.npz", num=60, steps=16, agents=3, mask=True)
    proc = dider_run(*TINY_RUN, f"data.source.path={root / 'train.npz'}", f"hydra.run.dir={root / 'run'}", cwd=root)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return root / "run"


def snapshot(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (hidden ones too) -> its content's hash."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------------------- the command-line rows


def _predict(tmp: Path, run: Path, npz: Path, *extra: str) -> list[str]:
    return ["mode=predict", f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}", "data=trajectories",
            f"data.source.path={npz}", "logger=none", "trainer.enable_progress_bar=false",
            f"hydra.run.dir={tmp / 'out'}",
            *extra]


def _npz(tmp: Path, name: str = "new.npz", scale: float = 1.0, steps: int = 12, nobody: bool = False) -> Path:
    arrays = write_trajectories(tmp / name, num=5, steps=steps, agents=4, seed=5)
    if scale != 1.0 or nobody:
        arrays["positions"] = arrays["positions"] * scale
        if nobody:
            arrays["mask"] = np.zeros(arrays["positions"].shape[:3], bool)
        np.savez(tmp / name, **arrays)
    return tmp / name


def crowd_table(tmp: Path) -> list[str]:
    """40 agents a window (1560 edges), string scene and agent ids."""
    rng = np.random.default_rng(0)
    s, a, f = np.meshgrid(np.arange(4), np.arange(40), np.arange(26), indexing="ij")
    walk = rng.normal(0, 0.3, (4, 40, 26, 2)).cumsum(2) + rng.uniform(0, 50, (4, 40, 1, 2))
    pd.DataFrame({"scene": [f"s{i}" for i in s.ravel()], "agent": [f"p{i}" for i in a.ravel()], "frame": f.ravel(),
                  "x": walk[..., 0].ravel(), "y": walk[..., 1].ravel()}).to_csv(tmp / "crowd.csv", index=False)
    return ["data=table", f"data.source.path={tmp / 'crowd.csv'}", "data.windows.seq_len=12", "data.windows.stride=12",
            "protocol.burn_in=4",
            "protocol.horizons=[1,4]", "data.loader.batch_size=2", "data.loader.eval_batch_size=2",
            "model.num_edges=2"]


def finished_run_refused(tmp: Path, run: Path) -> list[str]:
    """A second fresh training (other overrides) into a copy of a finished run's folder (.hydra/, run.log)."""
    return [*TINY_RUN, f"data.source.path={run.parent / 'train.npz'}", "seed=2", f"hydra.run.dir={tmp / 'run_copy'}"]


def other_version(tmp: Path, run: Path) -> list[str]:
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    ckpt["dider"]["version"] = "9.1.0"
    torch.save(ckpt, tmp / "old.ckpt")
    args = _predict(tmp, run, _npz(tmp))
    return [a if not a.startswith("ckpt_path=") else f"ckpt_path={tmp / 'old.ckpt'}" for a in args]


def prediction_there(tmp: Path, run: Path) -> list[str]:
    (tmp / "out" / "predictions").mkdir(parents=True)
    (tmp / "out" / "predictions" / "forecast.csv").write_text("another model's forecast\n")
    return _predict(tmp, run, _npz(tmp))


def names_in_forecast(tmp: Path) -> None:
    table = pd.read_csv(tmp / "out" / "predictions" / "forecast.csv")
    segments = pd.read_csv(tmp / "out" / "predictions" / "segments.csv")
    assert {"scene", "agent_id"} <= set(table.columns) and set(table["scene"]) <= {"s0", "s1", "s2", "s3"}
    assert set(table["agent_id"]) <= set(segments["sender_id"]) | set(segments["receiver_id"])
    assert table["agent_id"].str.startswith("p").all()


@dataclass
class Row:
    """make(tmp, trained run) -> command-line arguments; ok: the exit status is 0; said: a pattern of what it
    prints (stdout and stderr); then(tmp): asserts what it must leave behind."""

    make: Callable[[Path, Path], list[str]]
    ok: bool
    said: str
    then: Callable[[Path], None] | None = None


def timelines_drawn(tmp: Path) -> None:
    """The figures come from the first test batch: data.loader.eval_batch_size=2 clips of 40 agents."""
    assert len(list((tmp / "out" / "figures").glob("timeline_*.png"))) == 2


def other_forecast_kept(tmp: Path) -> None:
    assert (tmp / "out" / "predictions" / "forecast.csv").read_text() == "another model's forecast\n"


def _unchanged(tmp: Path) -> None:
    assert snapshot(tmp / "run_copy") == json.loads((tmp / "before.json").read_text())


CLI = {
    "many-agents": Row(lambda tmp, run: ["experiment=smoke", "model=dnri", "logger=none",
                                         "trainer.enable_progress_bar=false", f"hydra.run.dir={tmp / 'out'}",
                                         *crowd_table(tmp)],
                       True, r"metrics: .*metrics\.json[\s\S]*figures: ", timelines_drawn),
    "predict-into-a-prediction": Row(prediction_there, False, r"out/predictions already holds a prediction",
                                     other_forecast_kept),
    "predict-burn-in-longer-than-clips": Row(
        lambda tmp, run: _predict(tmp, run, _npz(tmp), "predict.forecast_steps=2", "predict.burn_in=50"), False,
        r"predict\.burn_in=50: longer than the 11 steps of the clips of data\.source\.path=.*new\.npz"),
    "predict-one-step-clips": Row(lambda tmp, run: _predict(tmp, run, _npz(tmp, steps=2)), False,
                                  r"its clips give 1 step\(s\) of the model's input; the model needs >= 2"),
    "predict-unit-mismatch": Row(lambda tmp, run: _predict(tmp, run, _npz(tmp, scale=1e6)), True,
                                 r"positions span \[.*\], about \d+x the training data's .*other units"),
    "predict-nobody-present": Row(lambda tmp, run: _predict(tmp, run, _npz(tmp, nobody=True)), True,
                                  r"no agent is present at any frame; the outputs will be empty"),
    "predict-other-version": Row(other_version, True, r"written by dider 9\.1\.0, this is "),
    "predict-run-folder-as-checkpoint": Row(
        lambda tmp, run: [a if not a.startswith("ckpt_path=") else f"ckpt_path={run}"
                          for a in _predict(tmp, run, _npz(tmp))], True, r"predictions: .*segments\.csv"),
    "predict-ind-short-clips": Row(
        lambda tmp, run: [*_predict(tmp, run, _npz(tmp))[:3], "data=ind",
                          f"data.source.root={write_ind_root(tmp / 'inD', num_recordings=1, num_frames=200)}",
                          "data.windows.seq_len=10", "data.source.recordings=[0]", *_predict(tmp, run, _npz(tmp))[5:]],
        True, r"predictions: .*segments\.csv"),
    "predict-forecast-names-agents": Row(
        lambda tmp, run: ["mode=predict", f"ckpt_path={run}", *crowd_table(tmp)[:2], "data.windows.seq_len=12",
                          "data.windows.stride=12", "predict.forecast_steps=3", "logger=none",
                          "trainer.enable_progress_bar=false", f"hydra.run.dir={tmp / 'out'}"],
        True, r"predictions: .*forecast\.csv", names_in_forecast),
    "refused-run-leaves-the-folder": Row(finished_run_refused, False,
                                         r"run_copy already holds a run", _unchanged),
    "unwritable-mlflow-store": Row(lambda tmp, run: [*TINY_RUN, f"data.source.path={run.parent / 'train.npz'}",
                                                     "logger=mlflow", f"logger.mlflow.tracking_uri=sqlite:///"
                                                     f"{run.parent / 'train.npz'}/mlflow.db",
                                                     f"hydra.run.dir={tmp / 'out'}"],
                                   False, r"logger\.mlflow\.tracking_uri=.*train\.npz is not a folder"),
}


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n == "many-agents" else n for n in CLI])
def test_command_line_probe(name, trained, tmp_path):
    row = CLI[name]
    import shutil

    shutil.copytree(trained, tmp_path / "run_copy")
    (tmp_path / "before.json").write_text(json.dumps(snapshot(tmp_path / "run_copy")))
    proc = dider_run(*row.make(tmp_path, trained), cwd=tmp_path)
    said = proc.stdout + proc.stderr
    assert (proc.returncode == 0) == row.ok, said[-3000:]
    assert re.search(row.said, said), said[-3000:]
    if row.then is not None:
        row.then(tmp_path)
    if not row.ok:  # a refusal or an input error leaves nothing half-written
        assert not (tmp_path / "out" / ".predictions.partial").exists()


# ----------------------------------------------------------------------------------------- the API rows

API = {  # method, arguments besides the positions, what the error must say
    "frame-rate-zero": ("segments", {"frame_rate": 0}, r"TrainedModel: frame_rate=0: must be > 0"),
    "frame-rate-negative": ("forecast", {"frame_rate": -10.0, "burn_in": 3, "steps": 2},
                            r"frame_rate=-10.0: must be > 0"),
    "burn-in-float": ("forecast", {"burn_in": 5.0, "steps": 2},
                      r"TrainedModel.forecast: burn_in=5.0: must be an integer"),
    "steps-float": ("forecast", {"burn_in": 5, "steps": 2.5}, r"steps=2.5: must be an integer"),
    "steps-bool": ("forecast", {"burn_in": 5, "steps": True}, r"steps=True: must be an integer"),
    "seed-negative": ("forecast", {"burn_in": 5, "steps": 2, "seed": -1},
                      r"seed=-1: must lie in \[0, 18446744073709551615\]"),
    "burn-in-too-long": ("forecast", {"burn_in": 40, "steps": 2}, r"burn_in=40: more than the 11 steps"),
    "one-step-clips": ("segments", {"frames": 2}, r"2 frame\(s\) a clip give 1 step\(s\).*>= 3 frames"),
    "one-step-probabilities": ("edge_probabilities", {"frames": 2}, r"needs >= 2 \(one transition\)"),
}


@pytest.mark.parametrize("name", list(API))
def test_api_probe(name, trained):
    method, kwargs, said = API[name]
    kwargs = dict(kwargs)
    positions = np.random.default_rng(0).normal(size=(2, kwargs.pop("frames", 12), 3, 2)).cumsum(1)
    model = dider.load(trained)
    with pytest.raises(ValueError, match=said):
        getattr(model, method)(positions, **kwargs)


def test_api_warns_of_a_unit_mismatch(trained, caplog):
    positions = np.random.default_rng(0).normal(size=(2, 12, 3, 2)).cumsum(1)
    model = dider.load(trained)
    model.segments(positions)
    assert "about" not in caplog.text
    model.segments(positions * 1e5)
    assert re.search(r"positions: positions span .* about \d+x the training data's", caplog.text)


# ------------------------------------------------------------------- prediction folders, SIGTERM, eval


def test_a_killed_prediction_leaves_no_mixed_folder(trained, tmp_path, monkeypatch):
    """A prediction that dies between two writes leaves no predictions/ (only its staging folder), and the
    next one into the folder removes that and writes a complete set with complete.json."""
    from dider.outputs import prediction
    from dider.run import predict
    from test_predict import compose_cfg

    npz = _npz(tmp_path)
    args = ["experiment=smoke", *_predict(tmp_path, trained, npz, "predict.forecast_steps=3")]

    def dies(*a, **k):
        raise OSError("disk full")  # a failure after segments.csv and clips.npz, before forecast.csv

    monkeypatch.setattr(prediction, "forecast_frame", dies)
    with pytest.raises(OSError, match="disk full"):
        predict(compose_cfg(args, tmp_path / "out"))
    assert not (tmp_path / "out" / "predictions").exists()
    assert (tmp_path / "out" / ".predictions.partial" / "segments.csv").exists()
    monkeypatch.undo()
    written = predict(compose_cfg(args, tmp_path / "out"))
    assert not (tmp_path / "out" / ".predictions.partial").exists()
    complete = json.loads((tmp_path / "out" / "predictions" / "complete.json").read_text())
    assert sorted(complete["files"]) == sorted(p.name for p in written) and complete["clips"] == 5
    assert {"segments.csv", "clips.npz", "forecast.csv"} <= set(complete["files"])


def test_a_long_prediction_reports_progress_and_stops_on_sigterm(trained, tmp_path):
    arrays = write_trajectories(tmp_path / "many.npz", num=6000, steps=16, agents=4, seed=2)
    assert arrays["positions"].shape[0] == 6000
    args = _predict(tmp_path, trained, tmp_path / "many.npz", "predict.forecast_steps=5", "predict.progress_s=0.5",
                    "data.loader.eval_batch_size=8")
    proc = subprocess.Popen([sys.executable, "-m", "dider.run", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, cwd=tmp_path)
    lines = []
    deadline = time.monotonic() + 240
    for line in proc.stdout:  # the log, as a file it is redirected to would get it
        lines.append(line)
        if re.search(r"predict: batch \d+ of 750 \(\d+%\), \d+ s, about \d+ s left", line):
            break
        assert time.monotonic() < deadline, "".join(lines)[-3000:]
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 143, out[-3000:]
    assert "terminated (SIGTERM or Ctrl-C) before the predictions were complete: nothing written to" in out
    assert "predict again with: python -m dider.run mode=predict" in out
    assert not (tmp_path / "out" / "predictions").exists() and not (tmp_path / "out" / ".predictions.partial").exists()


def test_eval_records_the_checkpoints_version(trained, tmp_path):
    proc = dider_run(*TINY_RUN, f"data.source.path={trained.parent / 'train.npz'}", "mode=eval",
                     f"ckpt_path={trained / 'checkpoints' / 'last.ckpt'}", f"hydra.run.dir={tmp_path / 'eval'}",
                     cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    record = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert record["checkpoint_version"] == dider.__version__ and "written by dider" not in proc.stderr
    assert (tmp_path / "eval" / ".hydra" / "overrides.yaml").exists() and (tmp_path / "eval" / "run.log").exists()
