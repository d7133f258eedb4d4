"""data=soccer: real tracking samples of several providers, read through kloppy from the files it ships."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

kloppy = pytest.importorskip("kloppy")

from dider.data.readers.kloppy import PROVIDERS, kloppy_tracking, tracking_rows  # noqa: E402
from dider.data.tracks import TracksDataModule  # noqa: E402

KLOPPY = "dider.data.track_sources.KloppySource"

FILES = Path(kloppy.__file__).parent / "tests" / "files"
HAWKEYE = {"ball_feeds": str(FILES / "hawkeye_1_1.football.samples.ball"),
           "player_centroid_feeds": str(FILES / "hawkeye_1_1.football.samples.centroids")}
HAWKEYE_2 = {"ball_feeds": str(FILES / "hawkeye_2_46.football.samples.ball"),
             "player_centroid_feeds": str(FILES / "hawkeye_2_46.football.samples.centroids")}
SAMPLES = {  # provider -> (files, frames per second): every tracking sample kloppy ships that reads quickly
    "hawkeye": (HAWKEYE, 50.0),
    "metrica_csv": ({"home_data": "metrica_home.csv", "away_data": "metrica_away.csv"}, 25.0),
    "metrica_epts": ({"meta_data": "epts_metrica_metadata.xml", "raw_data": "epts_metrica_tracking.txt"}, 25.0),
    "tracab": ({"meta_data": "tracab_meta.xml", "raw_data": "tracab_raw.dat"}, 25.0),
    "sportec": ({"meta_data": "sportec_meta.xml", "raw_data": "sportec_positional.xml"}, 25.0),
    "secondspectrum": ({"meta_data": "second_spectrum_fake_metadata.xml",
                        "raw_data": "second_spectrum_fake_data.jsonl"}, 25.0),
    "pff": ({"meta_data": "pff_metadata_10517.json", "roster_meta_data": "pff_rosters_10517.json",
             "raw_data": "pff_10517.jsonl"}, 29.97),
}


def sample(provider: str) -> dict[str, str]:
    return {k: str(FILES / v) for k, v in SAMPLES[provider][0].items()}


@pytest.mark.parametrize("provider", sorted(SAMPLES))
def test_every_provider_reads_into_metres(provider):
    """Players on the pitch (105 x 68 m, centred; a margin for run-offs), classes home / away, the provider's rate."""
    rows, rate = tracking_rows(kloppy_tracking(provider, sample(provider)), ball=True, source=provider)
    assert rate == pytest.approx(SAMPLES[provider][1], rel=1e-3)
    assert len(rows["frame"]) > 0 and rows["names"]["agent"][-1] == "ball"
    players = rows["agent_class"] != rows["names"]["agent_class"].index("ball")
    xy = rows["xy"][players]
    assert (np.abs(xy[:, 0]) < 60).all() and (np.abs(xy[:, 1]) < 42).all()
    assert np.ptp(xy[:, 0]) > 5  # metres, not a unit square
    assert set(np.unique(rows["agent_class"][players])) <= {0, 2}  # away, home
    key = np.stack([rows["scene"], rows["agent"], rows["frame"]], 1)
    assert len(np.unique(key, axis=0)) == len(key)  # one row per (period, agent, frame) ...
    assert (np.lexsort(key.T[::-1]) == np.arange(len(key))).all()  # ... sorted by them


def soccer(files: dict, **windows) -> TracksDataModule:
    """``data=soccer``'s module on Hawk-Eye's files (its window defaults: max_speed 12 m/s)."""
    return TracksDataModule(source={"_target_": KLOPPY, "provider": "hawkeye", "files": files},
                           windows={"max_speed": 12.0, **windows})


def test_hawkeye_windows_velocities_and_rate():
    """Downsampling 50 Hz by 8 gives 6.25 Hz steps; a velocity is the step's displacement x 6.25 (m/s)."""
    dm = soccer(HAWKEYE, downsample=8, seq_len=12, stride=12)
    dm.setup("fit")
    assert dm.hparams.source["frame_rate"] == 50.0 and dm.dt == pytest.approx(0.16)
    ds = dm.datasets["train"]
    raw = dm.normalizer.denormalize(ds.states)  # [P, T, 4] packed rows
    mask = ds.mask
    pos, vel = raw[..., :2], raw[..., 2:]
    both = mask[:, 1:] & mask[:, :-1]
    torch.testing.assert_close(vel[:, 1:][both], (pos[:, 1:] - pos[:, :-1])[both] * 6.25, atol=1e-3, rtol=1e-3)
    speeds = vel[mask].norm(dim=-1)
    assert speeds.max() < 12.0  # m/s: nobody outruns a sprinter
    assert ds.class_names == ["away", "ball", "home"]


@pytest.mark.parametrize("kwargs, match", [
    ({"provider": "statsbomb"}, r"data.source.provider='statsbomb': expected one of"),
    ({"files": {"ball_feeds": "x"}},
     r"data.source.files: data.source.provider=hawkeye needs \['player_centroid_feeds'\]"),
    ({"files": {**HAWKEYE, "raw_data": "r.dat"}}, r"data.source.files: unknown key\(s\) \['raw_data'\] for "
                                                 r"data.source.provider=hawkeye .*optionally \['meta_data'\]"),
    ({"files": {**HAWKEYE, "ball_feeds": "/no/such.ball"}},
     r"data.source.files.ball_feeds=/no/such.ball: no such file"),
    ({"files": HAWKEYE, "frame_rate": 25.0},
     r"data.source.frame_rate=25.0 \(given, or a checkpoint's in prediction\): the tracking data run at 50.0 frames"),
    ({"files": HAWKEYE, "frame_rate": float("nan")}, r"data.source.frame_rate=nan: must be null \(the provider's\)"),
    ({"files": "/data/match.xml"}, r"data.source.files='/data/match.xml': expected the reader's files by its "
                                   r"argument names, e.g. data.source.files=\{ball_feeds:PATH,player_centroid_feeds:"),
    ({"files": HAWKEYE, "options": {"sample_rat": 2}},
     r"data.source.options: kloppy.hawkeye.load takes no \['sample_rat'\]"),
])
def test_bad_input_is_named(kwargs, match):
    with pytest.raises((ValueError, FileNotFoundError), match=match):
        TracksDataModule(source={"_target_": KLOPPY, "files": HAWKEYE} | kwargs, windows={"seq_len": 12}).setup("fit")


def test_a_file_kloppy_cannot_read_is_named(tmp_path):
    bad = tmp_path / "garbage.xml"
    bad.write_text("not tracking data")
    files = {"meta_data": str(bad), "raw_data": str(FILES / "tracab_raw.dat")}
    with pytest.raises(ValueError,
                       match=r"data.source.files: kloppy.tracab.load could not read .* as data.source.provider=tracab"):
        kloppy_tracking("tracab", files)
    empty = tmp_path / "empty.dat"
    empty.write_text("")
    with pytest.raises(ValueError, match=r"data.source.files.raw_data=.*empty.dat: the file is empty"):
        kloppy_tracking("tracab", {"meta_data": str(FILES / "tracab_meta.xml"), "raw_data": str(empty)})


def test_every_provider_has_a_sample_here():
    """SkillCorner's sample takes ~10 s to read: covered by the recipe's runs, not here."""
    assert set(PROVIDERS) == set(SAMPLES) | {"skillcorner"}


def files_override(files: dict[str, str]) -> str:
    return "data.source.files={" + ",".join(f"{k}:'{v}'" for k, v in files.items()) + "}"


@pytest.mark.slow  # 15 s; the soccer recipe's training runs in the default set (test_experiments)
def test_train_then_predict_on_another_half(make_cfg, tmp_path):
    """`python -m dider.run data=soccer` trains on one Hawk-Eye sample and scores against constant velocity in
    metres; mode=predict reads the other sample at the rate the checkpoint carries (never given here)."""
    from dider.run import predict, train

    common = ["experiment=smoke", "data=soccer", "data.windows.downsample=8", "data.windows.seq_len=12",
              "data.windows.stride=6",
              "protocol.burn_in=5", "protocol.horizons=[1,5]", "logger=none",
              "trainer.enable_progress_bar=false", "callbacks.timelines.num_clips=0"]
    metrics = train(make_cfg([*common, files_override(HAWKEYE)], tiny=False, out=tmp_path / "run"))
    assert 0 < metrics["test/ade/h05"] and 0 < metrics["test/cv/ade/h05"]
    assert metrics["test/ade_vs_cv/h05"] == pytest.approx(metrics["test/ade/h05"] / metrics["test/cv/ade/h05"])
    ckpt = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert ckpt["dider"]["data"]["args"]["source"]["frame_rate"] == 50.0  # nested as the config nests it
    cfg = make_cfg([*common, files_override(HAWKEYE_2), "mode=predict", "predict.forecast_steps=6",
                    f"ckpt_path={tmp_path / 'run' / 'checkpoints' / 'last.ckpt'}"], tiny=False, out=tmp_path / "pred")
    written = {p.name for p in predict(cfg)}
    assert {"segments.csv", "clips.npz", "types.csv", "forecast_scores.json"} <= written
    scores = json.loads((tmp_path / "pred" / "predictions" / "forecast_scores.json").read_text())
    assert 0 < scores["predict/cv/ade/h05"] < 5.0  # metres after 0.8 s


def test_kloppy_sample_finds_the_files_kloppy_ships():
    from dider.data.readers.kloppy import kloppy_sample

    assert Path(kloppy_sample("tracab_meta.xml")) == FILES / "tracab_meta.xml"
    with pytest.raises(FileNotFoundError, match=r"kloppy_sample:nope.xml: kloppy .* ships no such sample"):
        kloppy_sample("nope.xml")
