"""Long-format trajectory tables (data=table): windows, masks, velocities, source ids, splits, predict, errors."""

import importlib.util
import json
import logging
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from dider.data.batch import Normalizer
from dider.data.common import SPLITS
from dider.data.pairs import PARKED
from dider.data.tracks import TracksDataModule
from dider.graph import edge_index
from helpers.data import merged

# The hand fixture. Scene 'east' (first in the file and by name): frames 0..5, agents amy and dan. Scene 'north':
# frames 10..17, bob at every frame, amy at every frame but 13 (a gap), cat from frame 14 on.
SPEED = {"amy": 1.0, "bob": 0.5, "cat": -1.0, "dan": 2.0}
X0 = {"amy": 0.0, "bob": 10.0, "cat": 20.0, "dan": 5.0}
Y0 = {"amy": 0.0, "bob": 1.0, "cat": 2.0, "dan": 3.0}
RATE = 2.0  # frames per second
TABLE = "dider.data.track_sources.TableFile"
SMALL = dict(source={"_target_": TABLE, "frame_rate": RATE}, windows={"seq_len": 4, "stride": 2},
             loader={"batch_size": 2, "eval_batch_size": 2})
COLUMNS = {"scene": "place", "agent": "who", "frame": "t", "x": "px", "y": "py"}
IDENTITY = Normalizer((-1.0, 1.0), (-1.0, 1.0))  # normalize() returns raw units: windows checked by value


def position(agent: str, frame: float) -> tuple[float, float]:
    return SPEED[agent] * frame + X0[agent], 0.1 * frame**2 + Y0[agent]


def hand_table() -> pd.DataFrame:
    spans = [("east", "amy", range(0, 6)), ("east", "dan", range(0, 6)), ("north", "bob", range(10, 18)),
             ("north", "amy", [f for f in range(10, 18) if f != 13]), ("north", "cat", range(14, 18))]
    rows = [{"place": s, "who": a, "t": f, "px": position(a, f)[0], "py": position(a, f)[1],
             "vx": SPEED[a], "vy": -SPEED[a], "kind": "car" if a == "dan" else "pedestrian", "note": "x"}
            for s, a, frames in spans for f in frames]
    df = pd.DataFrame(rows)
    # Rows out of order inside each scene (the reader sorts them), east's still first in the file.
    order = np.random.default_rng(0).permutation
    east, north = df[df.place == "east"], df[df.place == "north"]
    return pd.concat([east.iloc[order(len(east))], north.iloc[order(len(north))]], ignore_index=True)


@pytest.fixture
def table(tmp_path: Path) -> Path:
    path = tmp_path / "tracks.csv"
    hand_table().to_csv(path, index=False)
    return path


def make_dm(path: Path | None, columns: dict | None = None, **kw) -> TracksDataModule:
    """The module of the table at ``path`` read by ``columns`` (whole: ``COLUMNS`` by default), cut small
    (``SMALL``), ``kw`` (nested as the config nests them) over it key by key."""
    source = {"path": None if path is None else str(path), "columns": columns or COLUMNS}
    return TracksDataModule(**merged(merged(SMALL, {"source": source}), kw))


def windows(path: Path, normalizer: Normalizer = IDENTITY, **kw) -> tuple[TracksDataModule, object]:
    """Every window of the table (the predict setup), in raw units by default."""
    dm = make_dm(path, **kw)
    dm.use_normalizer(normalizer)
    dm.setup("predict")
    return dm, dm.datasets["predict"]


def rows_of(ds, w: int) -> slice:
    return slice(int(ds.offsets[w]), int(ds.offsets[w + 1]))


def expected(agent: str, frames: list[int], vel: str = "diff", span: int = 1) -> torch.Tensor:
    """[T, 4] raw states of an agent at those frames (velocities: differences over ``span`` frames at RATE,
    or the vx/vy columns)."""
    out = []
    for f in frames:
        (x, y), (px, py) = position(agent, f), position(agent, f - span)
        v = ((x - px) * RATE / span, (y - py) * RATE / span) if vel == "diff" else (SPEED[agent], -SPEED[agent])
        out.append([x, y, *v])
    return torch.tensor(out)


def test_windows_stride_mask_and_velocities(table):
    dm, ds = windows(table)
    # Differences drop each scene's first frame: east 1..5 (one window), north 11..17 (windows at 11, 13).
    assert ds.sources["clip"].tolist() == [0, 1, 2]
    assert ds.sources["frame"].tolist() == [1, 11, 13]
    assert ds.sources["scene"].tolist() == [0, 1, 1] and dm.source_names["scene"] == ["east", "north"]
    assert dm.source_names["agent"] == ["amy", "bob", "cat", "dan"]
    # Agents by id; cat (from frame 14, needs 13 for a velocity) is absent from the window at 11.
    assert ds.offsets.tolist() == [0, 2, 4, 7] and ds.agent_ids.tolist() == [0, 3, 0, 1, 0, 1, 2]
    want_mask = [[1, 1, 1, 1], [1, 1, 1, 1],  # east: amy, dan
                 [1, 1, 0, 0], [1, 1, 1, 1],  # north at 11: amy misses 13 and 14 (14 needs 13), bob
                 [0, 0, 1, 1], [1, 1, 1, 1], [0, 0, 1, 1]]  # north at 13: amy, bob, cat (velocity from 15)
    assert ds.mask.int().tolist() == want_mask
    names = ["amy", "dan", "amy", "bob", "amy", "bob", "cat"]
    starts = [1, 1, 11, 11, 13, 13, 13]
    for row, (agent, start) in enumerate(zip(names, starts, strict=True)):
        want = expected(agent, list(range(start, start + 4)))
        m = ds.mask[row]
        torch.testing.assert_close(ds.states[row][m], want[m], atol=1e-4, rtol=0)
        assert (ds.states[row][~m] == 0).all()
    assert dm.frame_step == 1 and dm.dt == pytest.approx(0.5)


def test_given_velocities_and_downsample(table):
    columns = {**COLUMNS, "vx": "vx", "vy": "vy"}
    _, ds = windows(table, columns=columns)  # no step dropped: east 0..5, north 10..17
    assert ds.sources["frame"].tolist() == [0, 2, 10, 12, 14]
    lo = rows_of(ds, 2)  # north at 10: amy (absent at 13 only), bob; cat (from 14) is not in it
    assert ds.agent_ids[lo].tolist() == [0, 1] and ds.mask[lo].int().tolist() == [[1, 1, 1, 0], [1, 1, 1, 1]]
    torch.testing.assert_close(ds.states[lo][1], expected("bob", [10, 11, 12, 13], vel="given"))
    # downsample=2: north keeps frames 10, 12, 14, 16 (13 is skipped, amy has no gap); differences span 2
    # frames at RATE / 2; east (0, 2, 4 -> 2 steps after the drop) is too short for seq_len=3.
    dm, ds = windows(table, windows={"downsample": 2, "seq_len": 3})
    assert ds.sources["frame"].tolist() == [12] and dm.frame_step == 2 and dm.dt == pytest.approx(1.0)
    assert ds.agent_ids.tolist() == [0, 1, 2] and ds.mask.int().tolist() == [[1, 1, 1], [1, 1, 1], [0, 0, 1]]
    torch.testing.assert_close(ds.states[0], expected("amy", [12, 14, 16], span=2), atol=1e-4, rtol=0)


def test_steps_faster_than_max_speed_are_absent(tmp_path, caplog):
    """A jump of the tracking (bob teleports 30 m between frames 4 and 5) is one absent step, counted in a
    warning; the speeds around it and the other agents are kept."""
    rows = [{"agent": a, "frame": f, "x": 1.0 * f + (30.0 if a == "bob" and f >= 5 else 0.0), "y": float(a == "bob")}
            for a in ("amy", "bob") for f in range(9)]
    path = tmp_path / "jump.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    kw = dict(columns={"agent": "agent"}, windows={"seq_len": 8, "stride": 8}, source={"frame_rate": 2.0})
    _, kept = windows(path, **kw)
    assert kept.mask.all() and kept.states[..., 2].max() == pytest.approx(62.0)  # (30 + 1) m in half a second
    with caplog.at_level(logging.WARNING, logger="dider.data.table"):
        _, ds = windows(path, **merged(kw, {"windows": {"max_speed": 10.0}}))
    assert ds.agent_ids.tolist() == [0, 1]
    # steps are frames 1..8 (differences drop frame 0): bob's step at frame 5 moved 31 m in 0.5 s
    assert ds.mask.int().tolist() == [[1] * 8, [1, 1, 1, 1, 0, 1, 1, 1]]
    assert ds.states[1, 4].abs().sum() == 0 and ds.states[ds.mask][:, 2].tolist() == pytest.approx([2.0] * 15)
    assert "1 of 16 agent-steps (6.25%) move faster than data.windows.max_speed=10.0" in caplog.text
    with pytest.raises(ValueError, match="data.windows.max_speed=0"):
        make_dm(path, columns={"agent": "agent"}, windows={"max_speed": 0})


def test_min_agent_steps_and_min_agents(table):
    _, ds = windows(table, windows={"min_agent_steps": 3})  # amy and cat have 2 steps at 13, amy 2 at 11: bob alone
    assert ds.sources["frame"].tolist() == [1]
    _, ds = windows(table, windows={"min_agents": 3})
    assert ds.sources["frame"].tolist() == [13] and ds.sources["clip"].tolist() == [0]


def test_source_ids_map_back_to_the_rows(table):
    dm, ds = windows(table)
    batch = ds.__getitems__([0, 2])  # padded: agent -1 where there is no agent
    assert batch["source"]["agent"].tolist() == [[0, 3, -1], [0, 1, 2]] and batch["source"]["clip"].tolist() == [0, 2]
    assert batch["source"]["frame"].tolist() == [1, 13] and batch["source"]["scene"].tolist() == [0, 1]
    row, step = ds.mask.nonzero().unbind(1)
    window = torch.searchsorted(ds.offsets, row, right=True) - 1
    names = dm.source_names
    found = pd.DataFrame({
        "place": np.array(names["scene"])[ds.sources["scene"][window].numpy()],
        "who": np.array(names["agent"])[ds.agent_ids[row].numpy()],
        "t": (ds.sources["frame"][window] + step).numpy(),
        "x_got": ds.states[row, step, 0].numpy(), "y_got": ds.states[row, step, 1].numpy()})
    merged = found.merge(hand_table(), on=["place", "who", "t"], how="left", validate="many_to_one")
    assert merged.px.notna().all()  # every present entry is a row of the table ...
    np.testing.assert_allclose(merged.x_got, merged.px, atol=1e-4)  # ... with its values
    np.testing.assert_allclose(merged.y_got, merged.py, atol=1e-4)


def test_integer_ids_and_one_scene(tmp_path):
    df = hand_table()
    df["who"] = df.who.map({"amy": 7, "bob": 3, "cat": 11, "dan": 5})
    df = df[df.place == "north"].drop(columns="place")
    df.to_csv(tmp_path / "t.csv", index=False)
    columns = {k: v for k, v in COLUMNS.items() if k != "scene"}
    dm, ds = windows(tmp_path / "t.csv", columns=columns)
    assert dm.source_names == {} and set(ds.sources) == {"clip", "frame"}
    assert ds.agent_ids.tolist() == [3, 7, 3, 7, 11]  # original ids, in id order


def test_a_column_called_scene_is_read_as_the_scene(tmp_path, table, caplog):
    """data.source.columns.scene unset and a column named "scene": it splits the scenes, and the log says so."""
    hand_table().rename(columns={"place": "scene"}).to_csv(tmp_path / "t.csv", index=False)
    _, named = windows(table)
    with caplog.at_level("INFO", logger="dider.data.table_reading"):
        _, found = windows(tmp_path / "t.csv", columns={k: v for k, v in COLUMNS.items() if k != "scene"})
    assert "column 'scene' read as the scene id" in caplog.text
    assert found.sources["scene"].tolist() == named.sources["scene"].tolist() == [0, 1, 1]
    torch.testing.assert_close(found.states, named.states)


def test_agent_class(table):
    _, ds = windows(table, columns={**COLUMNS, "agent_class": "kind"})
    assert ds.class_names == ["car", "pedestrian"] and ds.agent_class.tolist() == [1, 0, 1, 1, 1, 1, 1]


def table_of_scenes(path: Path, scenes: int, frames: int = 13, agents: int = 3) -> Path:
    rng = np.random.default_rng(1)
    grid = np.stack(np.meshgrid(np.arange(scenes), np.arange(agents), np.arange(frames), indexing="ij"), -1)
    grid = grid.reshape(-1, 3)
    walk = rng.normal(0, 1, (len(grid), 2)).cumsum(0)
    pd.DataFrame({"place": 100 + grid[:, 0], "who": grid[:, 1], "t": grid[:, 2], "px": walk[:, 0],
                  "py": walk[:, 1]}).to_csv(path, index=False)
    return path


def test_the_split_does_not_depend_on_the_rows_order(tmp_path):
    """The same table with its rows shuffled across scenes: the same scenes in each split, the same windows."""
    path = table_of_scenes(tmp_path / "t.csv", scenes=5)
    shuffled = tmp_path / "shuffled.csv"
    df = pd.read_csv(path)
    df.iloc[np.random.default_rng(3).permutation(len(df))].to_csv(shuffled, index=False)
    splits = []
    for p in (path, shuffled):
        dm = make_dm(p, windows={"stride": 4})
        dm.setup()
        splits.append({s: (dm.datasets[s].sources["scene"].tolist(), dm.datasets[s].states) for s in SPLITS})
    for s in SPLITS:
        assert splits[0][s][0] == splits[1][s][0]
        assert torch.equal(splits[0][s][1], splits[1][s][1])


@pytest.mark.parametrize("scenes, by", [(5, "scene"), (2, "window")])
def test_split(tmp_path, caplog, scenes, by):
    path = table_of_scenes(tmp_path / "t.csv", scenes)
    dm = make_dm(path, windows={"stride": 4})  # 12 steps after the drop: 3 windows a scene
    with caplog.at_level(logging.INFO, logger="dider.data.tracks"):
        dm.setup()
    assert f"split by {by}" in caplog.text
    clips = {s: dm.datasets[s].sources["clip"] for s in ("train", "val", "test")}
    assert sorted(torch.cat(list(clips.values())).tolist()) == list(range(3 * scenes))  # 3 windows a scene
    if by == "scene":
        sets = [set(dm.datasets[s].sources["scene"].tolist()) for s in ("train", "val", "test")]
        assert not (sets[0] & sets[1] or sets[0] & sets[2] or sets[1] & sets[2])
        assert set.union(*sets) == set(range(100, 100 + scenes))
    train = dm.datasets["train"]
    present = train.states[train.mask]
    assert present.min() == pytest.approx(-1, abs=1e-5) and present.max() == pytest.approx(1, abs=1e-5)
    capped = make_dm(path, windows={"stride": 4}, num_train=2)
    capped.setup()
    assert len(capped.datasets["train"]) == 2


def test_predict_every_window_with_the_given_normaliser(table):
    norm = Normalizer((-5.0, 30.0), (-3.0, 4.0))
    _, raw = windows(table)
    _, ds = windows(table, normalizer=norm)
    assert ds.sources["clip"].tolist() == list(range(len(raw)))
    torch.testing.assert_close(ds.states, torch.where(raw.mask[..., None], norm.normalize(raw.states), 0.0))
    with pytest.raises(ValueError, match="use_normalizer"):
        make_dm(table).setup("predict")


def test_parquet(tmp_path, table):
    path = tmp_path / "tracks.parquet"
    if importlib.util.find_spec("pyarrow") is None and importlib.util.find_spec("fastparquet") is None:
        path.write_bytes(b"PAR1")
        with pytest.raises(ImportError, match=r"pip install pyarrow"):
            windows(path)
        return
    df = hand_table()
    df.to_parquet(path)
    _, want = windows(table)
    _, got = windows(path)
    assert torch.equal(got.states, want.states) and torch.equal(got.agent_ids, want.agent_ids)
    df.loc[4, "px"] = np.nan
    df.to_parquet(path)
    with pytest.raises(ValueError, match=r"column 'px' has 1 empty, NaN or inf value\(s\) \(first on row 4"):
        windows(path)


def write(path: Path, edit) -> Path:
    df = hand_table().astype({"px": object, "t": object, "who": object})
    edit(df)
    df.to_csv(path, index=False)
    return path


def test_bad_input(tmp_path, table):
    p = tmp_path / "bad.csv"
    with pytest.raises(ValueError, match="data.source.path is not set"):
        windows(None)
    with pytest.raises(FileNotFoundError, match=r"bad.csv: no such file"):
        windows(p)
    with pytest.raises(ValueError, match=r"unknown extension '.txt'"):
        windows(tmp_path / "t.txt")
    with pytest.raises(ValueError, match=r"missing column\(s\) \['xpos'\] \(found \['place', 'who', 't', 'px'"):
        windows(table, columns={**COLUMNS, "x": "xpos"})
    cases = [
        (lambda d: d.loc.__setitem__((3, "px"), "abc"), r"column 'px' has 1 non-numeric value\(s\) \(first on "
                                                        r"line 5: 'abc'\)"),
        (lambda d: d.loc.__setitem__((6, "py"), np.nan), r"column 'py' has 1 empty, NaN or inf value\(s\) "
                                                         r"\(first on line 8"),
        (lambda d: d.loc.__setitem__((2, "px"), np.inf), r"column 'px' has 1 empty, NaN or inf .* line 4"),
        (lambda d: d.loc.__setitem__((5, "t"), 12.5), r"column 't' has non-integer frames \(first on line 7: 12.5"),
        (lambda d: d.loc.__setitem__((9, "who"), np.nan), r"column 'who' is empty on line 11"),
        (lambda d: d.drop(d.index, inplace=True), r"no rows"),
    ]
    for edit, match in cases:
        with pytest.raises(ValueError, match=match):
            windows(write(p, edit))
    # a duplicate (scene, agent, frame): both lines named
    df = hand_table()
    pd.concat([df, df.iloc[[3]]], ignore_index=True).to_csv(p, index=False)
    who, t = df.who[3], df.t[3]
    with pytest.raises(ValueError, match=rf"duplicate rows for \('place', 'who', 't'\) = \('east', '{who}', "
                                         rf"{t}\) on line 5 and line {len(df) + 2}"):
        windows(p)
    df.loc[df.who == "bob", "kind"] = ["car", *["pedestrian"] * 7]
    df.to_csv(p, index=False)
    with pytest.raises(ValueError, match=r"more than one 'kind' for \('place', 'who', 't'\) = \('north', 'bob'"):
        windows(p, columns={**COLUMNS, "agent_class": "kind"})
    with pytest.raises(ValueError, match=r"too few frames for one window of data.windows.seq_len=9 steps: a window "
                                         r"needs 9 step\(s\) \+ 1 for the finite-difference velocities of "
                                         r"data.windows.downsample=1 frame\(s\), i.e. a scene spanning >= 10 frames, "
                                         r"and the longest scene has 8 step\(s\): set data.windows.seq_len <= 7$"):
        windows(table, windows={"seq_len": 9})
    with pytest.raises(ValueError,
                       match=r"no window of data.windows.seq_len=4 steps has >= data.windows.min_agents=4"):
        windows(table, windows={"min_agents": 4})
    df[df.t % 2 == 0].to_csv(p, index=False)  # frames 0, 2, 4, ...: no two consecutive steps for a velocity
    with pytest.raises(ValueError, match=r"no window .* \(frames step by 2: set data.windows.downsample=2\?\)"):
        windows(p, windows={"seq_len": 2})
    df[df.t <= 1].to_csv(p, index=False)  # two frames a scene: one step once the velocities are differenced
    with pytest.raises(ValueError, match=r"the longest scene has 2 step\(s\): no scene is long enough for the "
                                         r"shortest window \(data.windows.seq_len=2\)$"):
        windows(p, windows={"seq_len": 2})  # not "set data.windows.seq_len <= 1", below the setting's minimum
    p.write_bytes(b"\x00\xff\xfe garbage")
    with pytest.raises(ValueError, match="bad.csv"):
        windows(p)


@pytest.mark.parametrize("kw, key", [
    ({"windows": {"seq_len": 1}}, "data.windows.seq_len"),
    ({"windows": {"seq_len": 2.5}}, r"data.windows.seq_len=2.5: must be an integer"),
    ({"windows": {"stride": 0}}, "data.windows.stride"), ({"source": {"frame_rate": 0}}, "data.source.frame_rate"),
    ({"windows": {"downsample": 0}}, "data.windows.downsample"),
    ({"windows": {"min_agent_steps": 5}}, "data.windows.min_agent_steps=5: must be <= data.windows.seq_len=4"),
    ({"windows": {"min_agents": 0}}, "min_agents"),
    ({"windows": {"eval_stride": 2}}, "data.windows.eval_stride=2: a table is cut before"),
    ({"split": (0.5, 0.5)}, "data.split"),
    ({"source": {"columns": {"speed": "v"}}}, r"data.source.columns: unknown key\(s\) \['speed'\]"),
    ({"source": {"columns": {"x": None}}}, "data.source.columns.x is null"),
    ({"source": {"columns": {"vx": "vx"}}}, "give both velocity columns"),
    ({"source": {"columns": {"x": "p", "y": "p"}}}, r"column\(s\) \['p'\] named for more than one key"),
])
def test_bad_config_names_the_key(kw, key):
    with pytest.raises(ValueError, match=key):
        TracksDataModule(**merged(SMALL, kw))


def test_command_line_run(tmp_path):
    """`python -m dider.run data=table ...` trains and tests, and its exports name the table's scenes."""
    path = table_of_scenes(tmp_path / "t.csv", scenes=4, frames=25)
    df = pd.read_csv(path)
    df.assign(place="scene_" + df.place.astype(str)).to_csv(path, index=False)
    cmd = [sys.executable, "-m", "dider.run", "data=table", f"data.source.path={path}", "experiment=smoke",
           "trainer.max_epochs=1", f"hydra.run.dir={tmp_path / 'run'}", "logger=none",
           "trainer.enable_progress_bar=false", "data.source.columns.scene=place", "data.source.columns.agent=who",
           "data.source.columns.frame=t", "data.source.columns.x=px", "data.source.columns.y=py",
           "data.windows.seq_len=12", "protocol.horizons=[1,5]"]
    proc = subprocess.run(cmd, env={**os.environ, "HYDRA_FULL_ERROR": "1"}, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())["metrics"]
    assert np.isfinite(metrics["test/mse/h01"]) and np.isfinite(metrics["test/mse/h05"])
    clips = json.loads((tmp_path / "run" / "segments.json").read_text())["clips"]
    assert {c["source"]["scene"] for c in clips} <= {f"scene_{i}" for i in range(100, 104)}


def test_a_window_too_long_fails_before_the_trainer_starts(make_cfg, tmp_path, monkeypatch):
    """13 frames a scene, velocities from differences: 12 steps. data.windows.seq_len=13 is named, with the arithmetic,
    before any training step (the trainer's fit is never entered)."""
    import lightning as L

    from dider.run import train

    path = table_of_scenes(tmp_path / "t.csv", scenes=3)

    def started(*args, **kwargs):
        raise AssertionError("the trainer started before the data were checked")

    monkeypatch.setattr(L.Trainer, "fit", started)
    cfg = make_cfg(["data=table", f"data.source.path={path}", "data.source.columns.scene=place",
                    "data.source.columns.agent=who", "data.source.columns.frame=t", "data.source.columns.x=px",
                    "data.source.columns.y=py", "data.windows.seq_len=13", "protocol.burn_in=4",
                    "protocol.horizons=[1,5]"])
    with pytest.raises(ValueError, match=r"a scene spanning >= 14 frames, and the longest scene has 13 step\(s\): "
                                         r"set data.windows.seq_len <= 12"):
        train(cfg)


def test_the_readme_own_data_commands_run_on_the_example(tmp_path):
    """The README's three own-data commands, as written, on the example tables it points to (training cut to one
    epoch): a run, a prediction and an explorer page."""
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = re.search(r"## Your data in three commands\n\n```bash\n(.*?)```", readme, re.S).group(1)
    commands = [line.split("#")[0].split() for line in block.strip().splitlines()]
    programs = [c[:3] for c in commands]
    assert programs == [["python", "-m", "dider.run"]] * 2 + [["python", "-m", "dider.analysis.explore"]]
    env = {**os.environ, "HYDRA_FULL_ERROR": "1"}
    for path, seed in (("tracks.csv", "0"), ("new.csv", "1")):
        subprocess.run([sys.executable, "-m", "dider.data.example", path, "--seed", seed], cwd=tmp_path, check=True,
                       env=env, capture_output=True)
    fast = ["trainer.max_epochs=1", "logger=none", "trainer.enable_progress_bar=false",
            "callbacks.timelines.num_clips=0"]
    for i, command in enumerate(commands):
        args = [sys.executable, *command[1:], *(fast if i == 0 else [])]
        done = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, f"{' '.join(command)}:\n{done.stderr[-3000:]}"
    assert (tmp_path / "runs" / "mine" / "explorer.html").exists()


def test_a_table_with_classes_gets_the_consistency_check(tmp_path):
    """``data.pairs`` on a table: its test windows carry the pairs of parked vehicles (two cars that never move), as
    inD's do; a table without classes is refused, naming ``data.pairs``."""
    rows = [{"place": scene, "who": agent, "t": f, "px": 5.0 * agent + speed * f, "py": scene + 0.5 * speed * f,
             "kind": kind}
            for scene in range(3) for agent, kind, speed in ((0, "car", 0.0), (1, "car", 0.0), (2, "pedestrian", 1.0))
            for f in range(12)]
    path = tmp_path / "t.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    dm = make_dm(path, columns={**COLUMNS, "agent_class": "kind"}, pairs={})
    dm.setup("fit")
    batch = next(iter(dm.test_dataloader()))
    send, recv = edge_index(batch["states"].shape[2])
    cars = (send < 2) & (recv < 2)
    assert (batch["pair_kind"][:, cars] == PARKED).all() and not (batch["pair_kind"][:, ~cars] == PARKED).any()
    assert "pair_kind" not in next(iter(dm.train_dataloader()))
    with pytest.raises(ValueError, match="data.pairs: the consistency check needs the agents' classes"):
        make_dm(path, pairs={}).setup("fit")
    _, ds = windows(path, pairs={})  # prediction has no test split: no pairs, and no classes needed
    assert ds.pairs is None and len(ds) == 12
