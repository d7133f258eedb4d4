"""inD / levelXdata reader: files in the exact format, DNRI protocol, masks, normalisation, cache, errors."""

import os
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
import torch
from hydra.utils import instantiate

from dider.bench.data import benchmark_preprocess
from dider.bench.fake_levelx import RECORDING_META_COLUMNS, TRACKS_COLUMNS, TRACKS_META_COLUMNS
from dider.data.clip_splits import split_counts
from dider.data.levelx import tracks as ind_mod
from dider.data.levelx.recordings import discover_recordings
from dider.data.tracks import TracksDataModule
from dider.protocol import burn_in_mask
from helpers.data import merged
from helpers.fixtures import edit_csv, write_background, write_ind_root

LEVELX_SOURCE = "dider.data.levelx.source.LevelXSource"

# 4 recordings of 600 frames (24 s at 25 Hz = 60 steps at 2.5 Hz), 6 tracks each, 2 parked.
SMALL = dict(split=(2, 1, 1), windows={"seq_len": 20}, loader={"batch_size": 4, "eval_batch_size": 4})
# The levelX module as its data config (data=ind) reads: DNRI's inD batches, the consistency check's default rules.
LEVELX = {"source": {"_target_": LEVELX_SOURCE}, "loader": {"batch_size": 8, "eval_batch_size": 8}, "pairs": {}}


@pytest.fixture
def root(tmp_path: Path) -> Path:
    return write_ind_root(tmp_path / "inD")


def levelx(**settings: Any) -> TracksDataModule:
    """The levelX module with ``settings`` (nested as the config nests them) over ``LEVELX`` key by key."""
    return TracksDataModule(**merged(LEVELX, settings))


def recordings(ds) -> list[str]:
    """The recordings a split's windows come from."""
    return [ds.scenes[i] for i in ds.window_scene.unique().tolist()]


def make_dm(root: Path, cache: Path, setup: bool = True, **kw) -> TracksDataModule:
    """The recordings in ``root`` cut small (``SMALL``), ``kw`` over it key by key."""
    given = merged({"source": {"root": None if root is None else str(root)}, **SMALL}, kw)
    dm = levelx(cache_dir=str(cache), **given)
    if setup:
        dm.prepare_data()
        dm.setup()
    return dm


def downsampled(root: Path, rec: str, factor: int = 10) -> pd.DataFrame:
    df = pd.read_csv(root / f"{rec}_tracks.csv")
    return df[df.frame % factor == 0].assign(step=lambda d: d.frame // factor)


def test_fixture_has_the_real_headers(root):
    assert list(pd.read_csv(root / "00_tracks.csv", nrows=0).columns) == TRACKS_COLUMNS
    assert list(pd.read_csv(root / "00_tracksMeta.csv", nrows=0).columns) == TRACKS_META_COLUMNS
    assert list(pd.read_csv(root / "00_recordingMeta.csv", nrows=0).columns) == RECORDING_META_COLUMNS
    meta = pd.read_csv(root / "00_tracksMeta.csv")
    assert (meta.numFrames == meta.finalFrame - meta.initialFrame + 1).all()
    tracks = pd.read_csv(root / "00_tracks.csv")
    initial = tracks.trackId.map(meta.set_index("trackId").initialFrame)
    assert (tracks.trackLifetime == tracks.frame - initial).all()
    vru = meta["class"].isin(["pedestrian", "bicycle"])
    assert (meta[vru][["width", "length"]] == 0).all().all()


def test_windows_match_the_csv_rows(root, tmp_path):
    dm = make_dm(root, tmp_path / "cache")
    train = dm.datasets["train"]
    assert recordings(train) == ["00", "01"] and recordings(dm.datasets["val"]) == ["02"]
    assert recordings(dm.datasets["test"]) == ["03"] and dm.dt == pytest.approx(0.4)
    # 60 steps per recording, non-overlapping 20-step windows: 3 per recording.
    assert len(train) == 6 and train.window_start.tolist() == [0, 20, 40] * 2
    rows = downsampled(root, "00")
    for w in range(3):  # every agent row of recording 00's windows equals the CSV at frames 10 * step
        lo, hi = int(train.offsets[w]), int(train.offsets[w + 1])
        start = int(train.window_start[w])
        inside = rows[(rows.step >= start) & (rows.step < start + 20)]
        assert train.agent_ids[lo:hi].tolist() == sorted(inside.trackId.unique())
        for j, tid in enumerate(train.agent_ids[lo:hi].tolist()):
            tr = inside[inside.trackId == tid]
            t = torch.as_tensor(tr.step.to_numpy() - start)
            want = torch.as_tensor(tr[["xCenter", "yCenter", "xVelocity", "yVelocity"]].to_numpy(),
                                   dtype=torch.float32)
            got = dm.normalizer.denormalize(train.states[lo + j, t])
            torch.testing.assert_close(got, want, atol=1e-3, rtol=0)
            assert train.mask[lo + j].nonzero().squeeze(1).tolist() == t.tolist()


def test_batches_are_padded_masked_and_finite(root, tmp_path):
    dm = make_dm(root, tmp_path / "cache")
    ds = dm.datasets["train"]
    batch = next(iter(dm.train_dataloader()))
    assert set(batch) == {"states", "mask", "source", "everyone"} and batch["states"].dtype == torch.float32
    b, t, n, f = batch["states"].shape
    # where each window came from: its recording (00 or 01 in train), its first frame, its track ids
    source = batch["source"]
    assert set(source) == {"clip", "scene", "frame", "agent"} and source["agent"].shape == (b, n)
    assert set(source["scene"].tolist()) <= {0, 1} and (source["frame"] % dm.windows.downsample == 0).all()
    assert ((source["agent"] >= 0) == batch["mask"].any(1)).all()  # padded agents: id -1
    assert (b, t, f) == (4, 20, 4) and batch["mask"].shape == (b, t, n) and batch["mask"].dtype == torch.bool
    assert torch.isfinite(batch["states"]).all()
    assert (batch["states"][~batch["mask"]] == 0).all()  # absent / padded agents: zeros, never NaN
    # The vectorised batch gather equals padding the single clips.
    idx = [5, 0, 3]
    many = ds.__getitems__(idx)
    n_max = int(ds.num_agents[idx].max())
    assert many["states"].shape == (3, 20, n_max, 4)
    for i, k in enumerate(idx):
        one = ds[k]
        m = one["mask"].shape[1]
        assert torch.equal(many["states"][i, :, :m], one["states"])
        assert torch.equal(many["mask"][i, :, :m], one["mask"])
        assert not many["mask"][i, :, m:].any()
    from dider.data.common import pad_collate
    listed = pad_collate([ds[k] for k in idx])
    assert torch.equal(listed["states"], many["states"]) and torch.equal(listed["mask"], many["mask"])


def test_masks_parked_and_entering_agents(root, tmp_path):
    dm = make_dm(root, tmp_path / "cache")
    ds = dm.datasets["train"]
    meta = pd.read_csv(root / "00_tracksMeta.csv").set_index("trackId")
    lo, hi = int(ds.offsets[0]), int(ds.offsets[1])
    for j, tid in enumerate(ds.agent_ids[lo:hi].tolist()):
        steps = ds.mask[lo + j].nonzero().squeeze(1)
        first = int(np.ceil(meta.initialFrame[tid] / 10))
        assert int(steps[0]) == max(first, 0) and int(steps[-1]) == min(meta.finalFrame[tid] // 10, 19)
        assert steps.numel() == int(steps[-1] - steps[0] + 1)  # contiguous
    # Parked vehicles (trackId 0, 1: present all recording, zero velocity) are in every window.
    parked = torch.isin(ds.agent_ids, torch.tensor([0, 1]))
    assert int(parked.sum()) == 2 * len(ds) and ds.mask[parked].all()
    raw = dm.normalizer.denormalize(ds.states[parked])
    assert raw[..., 2:].abs().max() < 1e-4
    # Per-agent burn-in helper: the first 5 present steps of each agent.
    bm = burn_in_mask(ds.mask[None, lo:hi].transpose(1, 2), 5)
    assert (bm.sum(1) == ds.mask[lo:hi].sum(1).clamp(max=5)).all()


def test_normalizer_fit_on_present_train_agents(root, tmp_path):
    dm = make_dm(root, tmp_path / "cache")
    rows = pd.concat([downsampled(root, r) for r in ("00", "01")])
    rows = rows[rows.step < 60]
    pos = rows[["xCenter", "yCenter"]].to_numpy()
    vel = rows[["xVelocity", "yVelocity"]].to_numpy()
    assert dm.normalizer.pos_range == pytest.approx((pos.min(), pos.max()), abs=1e-3)
    assert dm.normalizer.vel_range == pytest.approx((vel.min(), vel.max()), abs=1e-3)
    tr = dm.datasets["train"]
    present = tr.states[tr.mask]
    assert present.min() == pytest.approx(-1, abs=1e-5) and present.max() == pytest.approx(1, abs=1e-5)
    other = make_dm(root, tmp_path / "cache", split=(1, 2, 1))
    assert other.normalizer.pos_range != dm.normalizer.pos_range  # fitted on a different train split


def test_downsample_stride_and_window_filters(root, tmp_path):
    cache = tmp_path / "cache"
    dm = make_dm(root, cache, windows={"downsample": 5, "seq_len": 30})  # 120 steps: 4 windows
    assert len(dm.datasets["test"]) == 4 and dm.dt == pytest.approx(0.2)
    dm = make_dm(root, cache, windows={"stride": 5, "eval_stride": 40})  # train windows at 0, 5, ..., 40; eval at 0, 40
    assert dm.datasets["train"].window_start.tolist() == list(range(0, 41, 5)) * 2
    assert dm.datasets["val"].window_start.tolist() == [0, 40]
    full = make_dm(root, cache)
    capped = make_dm(root, cache, windows={"max_agents": 3})
    assert capped.datasets["train"].num_agents.max() == 3
    assert (capped.datasets["train"].num_agents == full.datasets["train"].num_agents.clamp(max=3)).all()
    # the cap keeps the agents present longest: the parked ones (whole windows) always survive
    ds = capped.datasets["train"]
    assert int(torch.isin(ds.agent_ids, torch.tensor([0, 1])).sum()) == 2 * len(ds)
    longer = make_dm(root, cache, windows={"min_agent_steps": 12})  # only agents present >= 12 of the 20 steps
    assert (longer.datasets["train"].mask.sum(1) >= 12).all()
    assert len(longer.datasets["train"].mask) < len(full.datasets["train"].mask)
    # min_agents drops the windows with fewer agents
    thr = min(int(d.num_agents.max()) for d in full.datasets.values())
    crowded = make_dm(root, cache, windows={"min_agents": thr}).datasets["train"]
    assert len(crowded) == int((full.datasets["train"].num_agents >= thr).sum())
    assert crowded.num_agents.min() >= thr


def test_class_filter_and_caps(root, tmp_path):
    cache = tmp_path / "cache"
    dm = make_dm(root, cache, source={"classes": ["car", "truck_bus"]})
    ds = dm.datasets["train"]
    assert set(np.array(ds.class_names)[ds.agent_class].tolist()) <= {"car", "truck_bus"}
    everyone = make_dm(root, cache).datasets["train"]
    assert len(set(np.array(everyone.class_names)[everyone.agent_class].tolist())) > 2
    capped = make_dm(root, cache, num_train=4, num_val=1)
    assert len(capped.datasets["train"]) == 4 and len(capped.datasets["val"]) == 1
    # evenly spread: both training recordings are still sampled
    assert set(capped.datasets["train"].window_scene.tolist()) == {0, 1}
    assert capped.datasets["train"].sources["clip"].tolist() == [0, 1, 2, 3]  # numbered in the split as capped


def test_splits_and_recording_selection(root, tmp_path):
    assert split_counts((19, 7, 7), 33) == (19, 7, 7)
    assert split_counts((0.6, 0.2, 0.2), 24) == (14, 5, 5)
    with pytest.raises(ValueError, match="asks for 33 recordings but only 4"):
        make_dm(root, tmp_path / "c", split=(19, 7, 7))
    with pytest.raises(ValueError, match="data.split"):
        levelx(split=(2, 0.5, 1))
    dm = make_dm(root, tmp_path / "c", split=(0.5, 0.25, 0.25))
    assert [recordings(dm.datasets[s]) for s in ("train", "val", "test")] == [["00", "01"], ["02"], ["03"]]
    recs = discover_recordings(root, recordings=[3, "01", 2])
    assert [r.id for r in recs] == ["01", "02", "03"]
    with pytest.raises(FileNotFoundError, match="recording 9"):
        discover_recordings(root, recordings=[9])


def test_default_is_dnri_protocol():
    dm = TracksDataModule(source={"_target_": LEVELX_SOURCE})
    assert list(dm.hparams.split) == [19, 7, 7] and dm.windows.downsample == 10 and dm.windows.seq_len == 50
    assert list(dm.source.columns.features) == ["xCenter", "yCenter", "xVelocity", "yVelocity"]
    assert dm.source.classes is None and dm.windows.min_agents == 2


def test_cache_is_shared_keyed_and_invalidated(root, tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    first = make_dm(root, cache)
    files = {p: p.stat().st_mtime_ns for p in (cache / "levelx").glob("*.pt")}
    assert len(files) == 4 and not list((cache / "levelx").glob(".*tmp"))

    def boom(*a, **k):
        raise AssertionError("re-read a cached recording")

    monkeypatch.setattr(ind_mod, "preprocess_recording", boom)
    again = make_dm(root, cache)  # same settings: everything from the cache
    assert {p: p.stat().st_mtime_ns for p in (cache / "levelx").glob("*.pt")} == files
    assert torch.equal(again.datasets["train"].states, first.datasets["train"].states)
    monkeypatch.undo()
    # A changed source file (mtime/size) and a changed parameter each give new cache entries.
    st = (root / "03_tracks.csv").stat()
    os.utime(root / "03_tracks.csv", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    make_dm(root, cache)
    assert len(list((cache / "levelx").glob("*.pt"))) == 5
    make_dm(root, cache, windows={"seq_len": 25})
    assert len(list((cache / "levelx").glob("*.pt"))) == 9


def test_extra_columns_ignored_and_custom_patterns(root, tmp_path):
    edit_csv(root / "00_tracks.csv",
             lambda d: d.assign(exportVersion="1.1")[["exportVersion", *d.columns[::-1]]])
    edit_csv(root / "00_recordingMeta.csv", lambda d: d.rename(columns={"numVRUs": "numVrus"}))
    base = make_dm(root, tmp_path / "c")
    assert len(base.datasets["train"]) == 6
    other = tmp_path / "round"
    other.mkdir()
    for p in root.iterdir():  # rename to a different naming scheme, e.g. round_00-tracks.csv
        rec, kind = p.name.split("_", 1)
        (other / f"round_{rec}-{kind}").write_bytes(p.read_bytes())
    dm = make_dm(other, tmp_path / "c2", source={"name": "round", "files": {
        "tracks": "round_{id}-tracks.csv", "tracks_meta": "round_{id}-tracksMeta.csv",
        "recording_meta": "round_{id}-recordingMeta.csv"}})
    assert torch.equal(dm.datasets["train"].states, base.datasets["train"].states)
    assert all(p.name.startswith("round_") for p in (tmp_path / "c2" / "levelx").glob("*.pt"))


def test_hydra_config_instantiates(root, make_cfg):
    cfg = make_cfg(["data=ind", f"data.source.root={root}", "data.split=[2,1,1]", "data.windows.seq_len=20",
                    "protocol.horizons=[1,5,15]"])
    dm = instantiate(cfg.data, _convert_="all")
    dm.prepare_data()
    dm.setup()
    batch = next(iter(dm.val_dataloader()))
    assert batch["states"].shape[1] == 20 and cfg.model.protocol.burn_in == 5
    for option in ("ind200", "round", "unid"):
        assert make_cfg([f"data={option}"]).data._target_ == "dider.data.tracks.TracksDataModule"
    rules = instantiate(make_cfg(["data=ind", "data.pairs.parked_speed=0.3"]).data, _convert_="all").pair_rules
    assert rules.parked_speed == 0.3 and rules.moving_speed == 2.0  # each rule a key of its own


def test_benchmark_runs_small(tmp_path):
    assert benchmark_preprocess(tmp_path, minutes=0.5, num_tracks=10, num_parked=2) > 0


# ------------------------------------------------------------------------------------------ bad input


def _drop(col):
    return lambda d: d.drop(columns=[col])


def _set(col, value, row=3):
    def fn(d):
        d = d.copy()
        d[col] = d[col].astype(object) if isinstance(value, str) else d[col].astype(float)
        d.loc[row, col] = value
        return d
    return fn


BAD = [
    ("00_tracks.csv", _drop("xVelocity"), ValueError, r"00_tracks.csv: missing column\(s\) \['xVelocity'\]"),
    ("00_tracksMeta.csv", _drop("class"), ValueError, r"00_tracksMeta.csv: missing column.*class"),
    ("00_recordingMeta.csv", _drop("frameRate"), ValueError, r"00_recordingMeta.csv: missing col.*frameRate"),
    ("00_tracks.csv", _set("yCenter", np.nan), ValueError, r"00_tracks.csv: column 'yCenter' .* line 5"),
    ("00_tracks.csv", _set("xVelocity", np.inf), ValueError, r"00_tracks.csv: column 'xVelocity'"),
    ("00_tracks.csv", _set("frame", 3.5), ValueError, r"00_tracks.csv: column 'frame'"),
    ("00_tracks.csv", _set("frame", "abc"), ValueError, r"00_tracks.csv: column 'frame', line \d+: 'abc' is not"),
    ("00_tracks.csv", lambda d: pd.concat([d, d.iloc[[7]]]), ValueError, r"duplicate row for \(trackId, fr"),
    ("00_tracksMeta.csv", lambda d: d.assign(numFrames=d.numFrames + 1), ValueError,
     r"00_tracksMeta.csv: column 'numFrames' inconsistent"),
    ("00_tracksMeta.csv", lambda d: d.assign(initialFrame=d.initialFrame + 1, finalFrame=d.finalFrame + 1),
     ValueError, r"column 'initialFrame' inconsistent"),
    ("00_tracksMeta.csv", lambda d: d.iloc[1:], ValueError, r"trackId\(s\) \[0\] have no row in 00_tracksM"),
    ("00_tracksMeta.csv", lambda d: pd.concat([d, d.iloc[[0]].assign(trackId=99)]), ValueError,
     r"trackId\(s\) \[99\] have no rows in 00_tracks.csv"),
    ("00_tracksMeta.csv", lambda d: pd.concat([d, d.iloc[[0]]]), ValueError, r"trackId 0 is listed more"),
    ("00_tracks.csv", lambda d: d[~((d.trackId == 0) & (d.frame == 100))], ValueError,
     r"numFrames.*trackId 0.*gaps"),
    ("00_recordingMeta.csv", _set("frameRate", 0.0, row=0), ValueError, r"frameRate' = 0.0: must be > 0"),
    ("01_recordingMeta.csv", _set("frameRate", 30.0, row=0), ValueError, r"different frame rates"),
]


@pytest.mark.parametrize("name, fn, exc, match", BAD, ids=[f"{b[0]}-{b[3][:28]}" for b in BAD])
def test_bad_input_names_file_and_column(root, tmp_path, name, fn, exc, match):
    edit_csv(root / name, fn)
    with pytest.raises(exc, match=match):
        make_dm(root, tmp_path / "cache")


def test_missing_files_and_paths(root, tmp_path):
    with pytest.raises(ValueError, match="data.source.root is not set"):
        make_dm(None, tmp_path / "c")  # type: ignore[arg-type]
    with pytest.raises(FileNotFoundError, match="no such folder"):
        make_dm(tmp_path / "nowhere", tmp_path / "c")
    with pytest.raises(FileNotFoundError, match="no files matching"):
        make_dm(tmp_path, tmp_path / "c")
    (root / "02_tracksMeta.csv").unlink()
    with pytest.raises(FileNotFoundError, match="02_tracksMeta.csv: missing"):
        make_dm(root, tmp_path / "c")
    (root / "01_tracks.csv").write_text("")
    with pytest.raises(ValueError, match="01_tracks.csv: empty file"):
        make_dm(root, tmp_path / "c", source={"recordings": [0, 1, 3]}, split=(1, 1, 1))


def test_empty_metadata_file(root, tmp_path):
    (root / "03_recordingMeta.csv").write_text("")
    with pytest.raises(ValueError, match="03_recordingMeta.csv: empty file"):
        make_dm(root, tmp_path / "c")


def test_too_short_and_bad_config(root, tmp_path):
    with pytest.raises(ValueError, match=r"no window of data.windows.seq_len=70 .* too short"):
        make_dm(root, tmp_path / "c", windows={"seq_len": 70})
    with pytest.raises(ValueError, match=r"data.source.classes=\['tram'\] left too few tracks"):
        make_dm(root, tmp_path / "c", source={"classes": ["tram"]})
    for kw, key in [({"windows": {"seq_len": 1}}, "data.windows.seq_len"),
                    ({"windows": {"downsample": 0}}, "data.windows.downsample"),
                    ({"windows": {"max_agents": 0}}, "data.windows.max_agents"),
                    ({"source": {"columns": {"features": ["xCenter"]}}}, "data.source.columns.features"),
                    ({"source": {"files": {"tracks": "tracks.csv"}}}, "data.source.files.tracks"),
                    ({"windows": {"max_speed": 30.0}}, "data.windows.max_speed=30.0: levelX tracks"),
                    ({"split": (1, 1)}, "data.split")]:
        with pytest.raises(ValueError, match=key):
            levelx(**merged(SMALL, kw))


def test_background_image_and_extent(root, tmp_path):
    dm = make_dm(root, tmp_path / "cache")
    assert dm.background("test", 0) is None  # no XX_background.png: no image
    write_background(root, "03", rows=90, cols=120)
    image, extent = dm.background("test", 0)
    meters = 0.0081464 * 12  # the fixture's orthoPxToMeter x the default background_scale
    assert image.shape[:2] == (90, 120)
    assert extent == pytest.approx((0.0, 120 * meters, -90 * meters, 0.0))
    assert dm.background("test", 1)[0] is image  # one read per recording: the figures draw many of its clips
