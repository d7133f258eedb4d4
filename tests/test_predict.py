"""Using a trained model on new data: self-describing checkpoints, dider.load, mode=predict, the API page's example."""

from __future__ import annotations

import json
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, open_dict

import dider
from dider.data.batch import Normalizer
from dider.run import predict, train, validate_config
from dider.trained import training_settings
from dider.validation import ConfigError
from helpers.data import data_module
from helpers.fixtures import write_trajectories

README = Path(__file__).resolve().parents[1] / "README.md"
API_PAGE = Path(__file__).resolve().parents[1] / "docs" / "api.md"
TINY = ["experiment=smoke", "data=trajectories", "data.num_val=4", "protocol.horizons=[1,5]",
        "data.source.frame_rate=10",
        "trainer.enable_progress_bar=false", "logger=none", "callbacks.timelines.num_clips=0"]


def compose_cfg(overrides: list[str], out: Path) -> DictConfig:
    GlobalHydra.instance().clear()
    with initialize_config_module(version_base="1.3", config_module="dider.conf"):
        cfg = compose(config_name="config", overrides=overrides, return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(out)
        cfg.hydra.job.num, cfg.hydra.job.id = 0, "test"
    HydraConfig().set_config(cfg)
    return cfg


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A one-epoch DIDER run on an npz whose last agent leaves half-way."""
    root = tmp_path_factory.mktemp("trained")
    write_trajectories(root / "train.npz", num=60, steps=16, agents=3, mask=True)
    train(compose_cfg([*TINY, f"data.source.path={root / 'train.npz'}"], root / "run"))
    GlobalHydra.instance().clear()
    return root / "run"


@pytest.fixture(scope="module")
def new_data(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, np.ndarray]]:
    """Unseen clips, no edges and no split: 7 clips of 4 agents, one leaving half-way."""
    path = tmp_path_factory.mktemp("new") / "new.npz"
    return path, write_trajectories(path, num=7, steps=12, agents=4, mask=True, seed=5)


def test_checkpoint_describes_itself(run):
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    meta = ckpt["dider"]
    assert meta["version"] == dider.__version__
    assert meta["data"]["features"] == ["x", "y", "vx", "vy"]
    assert meta["data"]["args"]["source"]["frame_rate"] == 10  # nested as the config nests it
    dm = data_module("trajectories", source={"path": meta["data"]["args"]["source"]["path"], "frame_rate": 10},
                     num_val=4)
    dm.setup("fit")  # the same file and split refit the same normaliser
    assert Normalizer(**meta["data"]["state"]["normalizer"]).state_dict() == dm.normalizer.state_dict()
    assert ckpt["hyper_parameters"]["net"]["name"] == "dider"


def test_load_gives_a_ready_model(run, new_data):
    path, arrays = new_data
    model = dider.load(run)
    assert model.path.parent == run / "checkpoints" and not model.network.training
    segs = model.segments(arrays["positions"], mask=arrays["mask"])  # frame_rate: the training data's
    assert list(segs.columns) == ["clip", "sender", "receiver", "segment", "start_step", "end_step", "start_frame",
                                  "end_frame", "type", "prob"]
    assert sorted(segs["clip"].unique()) == list(range(7))
    # Each present edge's segments tile its present transitions: 10 of the 11 steps (finite differences use
    # the first frame) for pairs of the three agents that stay, 5 for pairs with the one that leaves.
    span = segs.groupby(["clip", "sender", "receiver"]).agg(first=("start_step", "min"), last=("end_step", "max"),
                                                            steps=("end_step", "sum"))
    assert (span["first"] == 0).all()
    stays = (segs.groupby(["clip", "sender", "receiver"]).size().index.get_level_values("sender") < 3)
    ends = span["last"].to_numpy()
    leaving = ~stays | (span.index.get_level_values("receiver") == 3)
    assert (ends[~leaving] == 10).all() and (ends[leaving] == 5).all()
    assert (segs["start_frame"] == segs["start_step"] + 1).all()  # input frame index of the segment's first frame
    assert segs["type"].between(0, 1).all() and segs["prob"].between(0, 1).all()
    probs = model.edge_probabilities(arrays["positions"], mask=arrays["mask"])
    assert probs.shape == (7, 12, 10, 2) and np.allclose(probs.sum(-1), 1, atol=1e-5)
    one = model.segments(arrays["positions"][2], mask=arrays["mask"][2])  # a single clip [T, N, 2]
    pd.testing.assert_frame_equal(one.drop(columns="clip"),
                                  segs[segs["clip"] == 2].drop(columns="clip").reset_index(drop=True))


def test_forecast_reads_the_burn_in_only(run, new_data):
    _, arrays = new_data
    model = dider.load(run / "checkpoints" / "last.ckpt")
    pos, mask = arrays["positions"].copy(), arrays["mask"]
    future = model.forecast(pos, burn_in=4, steps=9, mask=mask)
    assert future.shape == (7, 9, 4, 2)
    assert np.isfinite(future[:, :, :3]).all()
    pos[:, 7:] += 100.0 * mask[:, 7:, :, None]  # frames after the burn-in (input frames 5.. are steps 4..)
    assert np.array_equal(model.forecast(pos, burn_in=4, steps=9, mask=mask), future, equal_nan=True)
    pos[:, 3] += 1.0  # a burn-in frame
    assert not np.allclose(model.forecast(pos, burn_in=4, steps=9, mask=mask)[:, :, :3], future[:, :, :3])


def test_predict_mode_writes_every_clip(run, new_data, tmp_path):
    path, arrays = new_data
    ckpt = run / "checkpoints" / "last.ckpt"
    # data.source.frame_rate left out (the data config's is 1.0): the checkpoint's 10 is used, as dider.load does
    given = [o for o in TINY if not o.startswith("data.source.frame_rate=")]
    cfg = compose_cfg([*given, "mode=predict", f"ckpt_path={ckpt}", f"data.source.path={path}",
                      "predict.forecast_steps=6",
                       "model=dnri"],  # ignored: the checkpoint's own model is used
                      tmp_path / "pred")
    validate_config(cfg)
    written = predict(cfg)
    out = tmp_path / "pred" / "predictions"
    assert {p.name for p in written} >= {"segments.csv", "clips.npz", "forecast.csv"}
    table = pd.read_csv(out / "segments.csv")
    expected = dider.load(ckpt).segments(arrays["positions"], mask=arrays["mask"])
    pd.testing.assert_frame_equal(table, expected, check_dtype=False, atol=1e-4)
    with np.load(out / "clips.npz", allow_pickle=False) as z:
        assert z["segments"].shape == (7, 12, 10) and z["step_probs"].shape == (7, 12, 10, 2)
        assert z["clip"].tolist() == list(range(7)) and str(z["model"]) == "dider"
        present = arrays["mask"][:, 1:]  # the model's frames: finite differences drop the first
        assert np.allclose(z["positions"][present], arrays["positions"][:, 1:][present], atol=1e-4)
        api = dider.load(ckpt).forecast(arrays["positions"], burn_in=5, steps=6, mask=arrays["mask"])
        assert np.allclose(z["forecast"], api, atol=1e-5)
    # the explorer reads the prediction run's clips.npz: every clip, every present agent
    from dider.analysis import explore

    assert explore.main([str(tmp_path / "pred")]) == 0
    page = (tmp_path / "pred" / "explorer.html").read_text()
    assert page.count('"row":') == 7 and "dider" in page
    # what each type means: a row per type in types.csv, the same line in the explorer's legend
    types = pd.read_csv(out / "types.csv")
    assert types["type"].tolist() == [0, 1] and types["share"].sum() == pytest.approx(1.0)
    held = types[types["share"] > 0]  # a type that never holds has no statistics (NaN)
    assert len(held) and (held["distance"] > 0).all() and held["relative_heading_deg"].between(0, 180).all()
    assert page.count("of edge-steps") == 2
    forecast = pd.read_csv(out / "forecast.csv")
    # every agent is present at the burn-in's last step (input frame 5; the fourth leaves at frame 6)
    assert len(forecast) == 7 * 6 * 4
    assert forecast["step"].min() == 5 and forecast["frame"].min() == 6
    # the clips hold the forecast's future: it is scored in the input's units, beside constant velocity
    scores = json.loads((out / "forecast_scores.json").read_text())
    with np.load(out / "clips.npz", allow_pickle=False) as z:
        pos, mask = arrays["positions"][:, 1:], arrays["mask"][:, 1:]  # the model's frames
        dist = np.linalg.norm(z["forecast"] - pos[:, 5:11], axis=-1)  # [S, 6, N]
    scored = mask[:, 5:11] & mask[:, 4:5]
    horizons = sorted(int(k.rsplit("/h", 1)[1]) for k in scores if k.startswith("predict/ade/h"))
    assert horizons and max(horizons) <= 6
    for h in horizons:
        assert scores[f"predict/ade/h{h:02d}"] == pytest.approx(dist[:, :h][scored[:, :h]].mean(), rel=1e-4)
        assert scores[f"predict/fde/h{h:02d}"] == pytest.approx(dist[:, h - 1][scored[:, h - 1]].mean(), rel=1e-4)
        ratio = scores[f"predict/ade/h{h:02d}"] / scores[f"predict/cv/ade/h{h:02d}"]
        assert scores[f"predict/ade_vs_cv/h{h:02d}"] == pytest.approx(ratio, rel=1e-5)


def test_predict_refuses_another_frame_rate_unless_forced(run, new_data, tmp_path):
    ckpt = run / "checkpoints" / "last.ckpt"
    given = [o for o in TINY if not o.startswith("data.source.frame_rate=")]
    cfg = compose_cfg([*given, "mode=predict", f"ckpt_path={ckpt}", f"data.source.path={new_data[0]}",
                       "data.source.frame_rate=4"], tmp_path / "pred")
    with pytest.raises(ConfigError, match=r"data.source.frame_rate=4: the checkpoint .*last.ckpt was trained with "
                                          r"data.source.frame_rate=10, .*predict.force=true"):
        predict(cfg)
    assert not (tmp_path / "pred" / "predictions").exists()  # refused before any work
    cfg = compose_cfg([*given, "mode=predict", f"ckpt_path={ckpt}", f"data.source.path={new_data[0]}",
                       "data.source.frame_rate=4", "predict.force=true"], tmp_path / "forced")
    assert {p.name for p in predict(cfg)} >= {"segments.csv", "clips.npz"}


def test_training_settings_take_the_checkpoints_unless_set():
    trained = SimpleNamespace(data={"frame_rate": 10.0, "downsample": 2, "seq_len": 20}, path="m.ckpt")
    given = {"frame_rate": 1.0, "downsample": 2, "seq_len": 8, "stride": 3}
    assert training_settings(trained, given, set()) == {"frame_rate": 10.0}  # seq_len does not shape features
    assert training_settings(trained, given | {"frame_rate": 10.0}, {"data.frame_rate"}) == {}
    with pytest.raises(ValueError, match=r"data.downsample=3: the checkpoint m.ckpt was trained with "
                                         r"data.downsample=2"):
        training_settings(trained, given | {"downsample": 3}, {"data.downsample"})
    assert training_settings(trained, given | {"downsample": 3}, {"data.downsample"}, force=True) == {
        "frame_rate": 10.0}
    assert training_settings(SimpleNamespace(data={}, path="m.ckpt"), given, set()) == {}  # nothing recorded
    jumps = SimpleNamespace(data={"max_speed": 12.0}, path="m.ckpt")  # which steps count as tracking jumps
    assert training_settings(jumps, {"max_speed": None}, set()) == {"max_speed": 12.0}
    # a data config with nodes: each key read where it lives, the paths returned; the checkpoint's flat record
    nested = {"source": {"frame_rate": 1.0}, "windows": {"downsample": 2, "max_speed": None}}
    assert training_settings(trained, nested, set()) == {"source.frame_rate": 10.0}
    with pytest.raises(ValueError, match=r"data.windows.downsample=3: the checkpoint m.ckpt was trained with "
                                         r"data.windows.downsample=2"):
        training_settings(trained, {"windows": {"downsample": 3}}, {"data.windows.downsample"})
    assert training_settings(jumps, nested, set()) == {"windows.max_speed": 12.0}


def test_older_and_foreign_checkpoints_are_named(run, tmp_path):
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    del ckpt["dider"]
    old = tmp_path / "old.ckpt"
    torch.save(ckpt, old)
    with pytest.raises(ValueError, match=r"old\.ckpt: written in checkpoint format 1 by a development version before "
                                         r"0\.2\.0: retrain it with this version"):
        dider.load(old)
    foreign = tmp_path / "notes.ckpt"
    foreign.write_text("not a checkpoint")
    with pytest.raises(ValueError, match=r"notes\.ckpt: not a readable dider checkpoint"):
        dider.load(foreign)
    with pytest.raises(FileNotFoundError, match="a run folder with no checkpoint"):
        dider.load(tmp_path)


def test_predict_needs_the_trained_normaliser(new_data):
    dm = data_module("trajectories", source={"path": str(new_data[0])})
    with pytest.raises(ValueError, match="trained model's normaliser"):
        dm.setup("predict")


@pytest.mark.parametrize("overrides, key", [(["mode=predict"], "ckpt_path"),
                                            (["mode=predict", "ckpt_path=last"], "ckpt_path=last"),
                                            (["predict.forecast_steps=0"], "predict.forecast_steps=0")])
def test_predict_config_errors_name_the_key(tmp_path, overrides, key):
    cfg = compose_cfg(["data=trajectories", f"data.source.path={README}", *overrides], tmp_path)
    with pytest.raises(ConfigError, match=re.escape(key)):
        validate_config(cfg)


def test_api_page_example_runs(run, new_data):
    block = re.search(r"```python\n(import numpy as np\nimport dider\n.*?)```", API_PAGE.read_text(), re.S)
    assert block, "docs/api.md: the 'use a trained model' example is missing"
    code = block.group(1).replace('"runs/RUN"', repr(str(run))).replace('"new.npz"',
                                                                                       repr(str(new_data[0])))
    scope: dict[str, object] = {}
    exec(compile(code, "docs/api.md", "exec"), scope)
    assert isinstance(scope["segs"], pd.DataFrame) and len(scope["segs"]) > 0
    assert scope["future"].shape[1:3] == (10, 4)


def test_predict_refuses_a_data_set_without_a_prediction_set(run, tmp_path):
    cfg = compose_cfg(["experiment=smoke", "mode=predict", f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}"],
                      tmp_path)
    with pytest.raises(ConfigError, match=r"data: data.source._target_=dider.data.simulators.push.Push has no "
                                          r"prediction set"):
        predict(cfg)


def test_a_second_prediction_into_a_live_folder_is_refused_before_any_work(run, new_data, tmp_path, monkeypatch):
    """The folder's lock is taken before the check that predictions/ is free: a prediction into a folder another live
    prediction holds stops at once, before reading the checkpoint or the data."""
    import os
    import socket

    from dider.training.run_lock import LOCK
    from dider.training.runfolder import RunRefused

    out = tmp_path / "shared"
    out.mkdir()
    (out / LOCK).write_text(json.dumps({"pid": os.getppid(), "host": socket.gethostname()}))  # a live writer

    def work(*args, **kwargs):
        raise AssertionError("the second prediction started working")

    monkeypatch.setattr("dider.run.load", work)
    cfg = compose_cfg(["mode=predict", f"ckpt_path={run}", "data=trajectories", f"data.source.path={new_data[0]}"], out)
    with pytest.raises(RunRefused, match=r"is being written by another run \(pid"):
        predict(cfg)
    assert sorted(p.name for p in out.iterdir()) == [LOCK]


def test_damaged_checkpoint_internals_and_ragged_inputs_are_named(run, tmp_path):
    """A checkpoint whose weights miss a tensor, whose model config names no class or whose normaliser is broken:
    each named with the file and the part. A ragged positions list: named as the argument."""
    good = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)

    def damaged(name: str, edit) -> Path:
        ckpt = {k: (dict(v) if isinstance(v, dict) else v) for k, v in good.items()}
        edit(ckpt)
        torch.save(ckpt, tmp_path / name)
        return tmp_path / name

    missing = damaged("missing.ckpt", lambda c: c["state_dict"].pop(next(iter(c["state_dict"]))))
    with pytest.raises(ValueError, match=r"missing\.ckpt: its weights \(state_dict\) do not fit .*Missing key"):
        dider.load(missing)
    target = damaged("target.ckpt", lambda c: c["hyper_parameters"].update(
        net={**c["hyper_parameters"]["net"], "_target_": "no.such.Model"}))
    with pytest.raises(ValueError, match=r"target\.ckpt: hyper_parameters\.net\._target_=.no\.such\.Model"):
        dider.load(target)
    broken = damaged("normaliser.ckpt", lambda c: c.update(dider={**c["dider"], "data": {
        **c["dider"]["data"], "state": {"normalizer": {"pos_range": [1.0, 0.0], "vel_range": [0.0, 1.0]}}}}))
    with pytest.raises(ValueError, match=r"normaliser\.ckpt: its data normaliser .* is damaged"):
        dider.load(broken)
    model = dider.load(run)
    ragged = [[[[0.0, 0.0]] * 3] * 12, [[[0.0, 0.0]] * 2] * 12]  # two clips of 3 and 2 agents
    with pytest.raises(ValueError, match=r"^positions: not a rectangular array of numbers"):
        model.segments(ragged, frame_rate=10)


def test_predict_takes_the_threads_setting(run, new_data, tmp_path):
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        predict(compose_cfg(["mode=predict", f"ckpt_path={run}", "data=trajectories", f"data.source.path={new_data[0]}",
                             "threads=1"], tmp_path / "pred"))
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_a_prediction_into_a_run_folder_goes_to_predict_name_and_leaves_the_runs_record(run, new_data, tmp_path):
    """hydra.run.dir set to the training run: the prediction writes to predict/<data config>/ there; the run's
    .hydra/ record (what report reads) and its run.log are byte for byte as they were."""
    import shutil

    folder = tmp_path / "run"
    shutil.copytree(run, folder)
    record = {p.relative_to(folder): p.read_bytes() for p in [*(folder / ".hydra").iterdir(), folder / "run.log"]}
    assert len(record) == 4
    predict(compose_cfg(["mode=predict", f"ckpt_path={folder}", "data=trajectories",
                         f"data.source.path={new_data[0]}"], folder))
    assert (folder / "predict" / "trajectories" / "predictions" / "clips.npz").is_file()
    assert not (folder / "predictions").exists()
    assert {k: (folder / k).read_bytes() for k in record} == record
    # a fresh folder takes the prediction itself; predict.name picks the subfolder's name
    predict(compose_cfg(["mode=predict", f"ckpt_path={folder}", "data=trajectories", "predict.name=new",
                         f"data.source.path={new_data[0]}"], folder))
    assert (folder / "predict" / "new" / "predictions" / "complete.json").is_file()


def test_sampled_futures_without_a_forecast_are_refused(run, new_data, tmp_path):
    with pytest.raises(ConfigError, match=r"predict.samples=3: sampled futures need predict.forecast_steps"):
        predict(compose_cfg(["mode=predict", f"ckpt_path={run}", "data=trajectories", "predict.samples=3",
                             f"data.source.path={new_data[0]}"], tmp_path / "out"))
    assert not (tmp_path / "out").exists()


def test_a_copied_or_moved_run_folder_loads_its_own_best_checkpoint(run, tmp_path):
    """metrics.json names the best checkpoint relative to the folder: a copy loads the copy's file, a moved folder
    its best epoch (not last.ckpt)."""
    import shutil

    record = json.loads((run / "metrics.json").read_text())
    assert not Path(record["checkpoint"]).is_absolute() and record["checkpoint"] != "checkpoints/last.ckpt"
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    assert dider.load(copy).path == copy / record["checkpoint"]
    moved = tmp_path / "moved"
    copy.rename(moved)
    assert dider.load(moved).path == moved / record["checkpoint"]


@pytest.mark.parametrize("content, why", [
    ("[1, 2]", r"metrics.json: not a run's record \(a JSON object with a 'metrics' object\)"),
    ('{"metrics": {"test/nll": 1.0}, "checkp', r"metrics.json: not JSON \(half-written"),
])
def test_an_unreadable_run_record_is_named(run, tmp_path, content, why):
    import shutil

    folder = tmp_path / "run"
    shutil.copytree(run, folder)
    (folder / "metrics.json").write_text(content)
    with pytest.raises(ValueError, match=why):
        dider.load(folder)


def test_a_checkpoint_whose_format_mark_is_no_number_is_named(run, tmp_path):
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    ckpt["dider"]["format"] = "abc"
    torch.save(ckpt, tmp_path / "odd.ckpt")
    with pytest.raises(ValueError, match=r"odd.ckpt: not a dider checkpoint \(its format mark dider.format='abc' "):
        dider.load(tmp_path / "odd.ckpt")


@pytest.mark.parametrize("planted", ["run.log", ".predictions.partial"])
def test_a_planted_link_in_the_folder_is_refused_before_any_write(run, new_data, tmp_path, planted):
    """A link in the run folder (to a file or folder outside it) would carry the prediction's writes there: refused,
    naming it, and the link's target untouched."""
    from dider.training.runfolder import RunRefused

    out, outside = tmp_path / "out", tmp_path / "outside"
    out.mkdir()
    outside.mkdir()
    target = outside / "victim" if planted == ".predictions.partial" else outside / "victim.txt"
    target.mkdir() if planted == ".predictions.partial" else target.write_text("keep me")
    (out / planted).symlink_to(target)
    with pytest.raises(RunRefused, match=rf"holds link\(s\) \['{out / planted} -> {target}'\]"):
        predict(compose_cfg(["mode=predict", f"ckpt_path={run}", "data=trajectories",
                             f"data.source.path={new_data[0]}"], out))
    assert sorted(p.name for p in outside.rglob("*")) == ["victim" if planted.startswith(".") else "victim.txt"]
    assert planted.startswith(".") or target.read_text() == "keep me"


def test_the_api_reads_clips_a_batch_at_a_time(run, new_data, caplog):
    """batch_size 2 over 7 clips: four network calls, the same segments as one batch, the forecast's shape, and a
    progress line for a long call (progress_s=0: after every batch)."""
    _, arrays = new_data
    whole = dider.load(run)
    small = dider.load(run)
    small.batch_size, small.progress_s = 2, 0.0
    calls = []
    infer = small.network.infer
    small.network.infer = lambda batch, **kw: calls.append(batch["states"].shape[0]) or infer(batch, **kw)
    with caplog.at_level("INFO", logger="dider.trained"):
        segs = small.segments(arrays["positions"], mask=arrays["mask"])
    assert calls == [2, 2, 2, 1] and "6 of 7 clips" in caplog.text
    pd.testing.assert_frame_equal(segs, whole.segments(arrays["positions"], mask=arrays["mask"]))
    assert small.forecast(arrays["positions"], burn_in=4, steps=5, mask=arrays["mask"]).shape == (7, 5, 4, 2)
    small.batch_size = 0
    with pytest.raises(ValueError, match=r"TrainedModel: batch_size=0: must be >= 1"):
        small.segments(arrays["positions"], mask=arrays["mask"])


@pytest.mark.parametrize("kwargs, named", [({"frame_rate": float("inf")}, r"frame_rate=inf: must be finite"),
                                           ({"seed": 2**64}, r"seed=18446744073709551616: must lie in")])
def test_api_arguments_are_named_as_the_caller_gave_them(run, new_data, kwargs, named):
    _, arrays = new_data
    with pytest.raises(ValueError, match=named):
        dider.load(run).forecast(arrays["positions"], burn_in=4, steps=3, mask=arrays["mask"], **kwargs)
