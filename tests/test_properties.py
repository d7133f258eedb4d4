"""Property-based tests (hypothesis) of the readers and the simulator on malformed input.

The contract: a bad file or parameter raises the project's own ValueError / FileNotFoundError naming the
file (and key or column) or the config key; never an exception from deep inside numpy / pandas / torch;
and no half-written cache file is ever left behind.
"""

from __future__ import annotations

import re
import tempfile
from pathlib import Path
from unittest import mock

import numpy as np
import pandas as pd
import pytest
import torch
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from dider.data.levelx.recordings import discover_recordings
from dider.data.readers.trajectories import load_trajectories
from dider.data.simulators.push import simulate_push
from dider.data.tracks import TracksDataModule
from dider.graph import num_edges
from dider.validation import ConfigError
from helpers.data import data_module
from helpers.fixtures import write_ind_root

LEVELX_SOURCE = "dider.data.levelx.source.LevelXSource"

FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None,
                derandomize=True)  # the same examples on every run: a failure in CI reproduces locally

ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True, width=64)
ODD_FLOATS = st.sampled_from([np.nan, np.inf, -np.inf, 1e39, -1e308, 0.0, 0.5, 3.0, -1.0])
RARELY = st.sampled_from([False] * 7 + [True])  # about one draw in eight (shrinks to False)


# ------------------------------------------------------------------------------------------ trajectories


@st.composite
def array_like(draw, shape: tuple[int, ...], kind: str) -> np.ndarray:
    """An array of ``shape`` (sometimes mangled) with mostly sensible, sometimes hostile contents."""
    if draw(RARELY):  # wrong shape: drop, add or resize a dimension
        dims = list(shape)
        op = draw(st.sampled_from(["drop", "add", "resize"]))
        if op == "drop" and dims:
            dims.pop(draw(st.integers(0, len(dims) - 1)))
        elif op == "add":
            dims.insert(draw(st.integers(0, len(dims))), draw(st.integers(0, 3)))
        elif dims:
            dims[draw(st.integers(0, len(dims) - 1))] = draw(st.integers(0, 4))
        shape = tuple(dims)
    dtype = draw(st.sampled_from({
        "float": [np.float64] * 8 + [np.float32, np.int16, np.uint64, np.complex64, "U2", np.bool_],
        "mask": [np.bool_] * 4 + [np.int8, np.float32, "U1"],
        "edges": [np.int64] * 4 + [np.float64, np.uint64, np.bool_],
    }[kind]))
    dt = np.dtype(dtype)
    if dt.kind == "f":
        sane = st.floats(-100, 100, width=dt.itemsize * 8)
        elements = st.one_of(sane, ODD_FLOATS) if dt.itemsize == 8 and draw(RARELY) else sane
        if kind == "mask":
            elements = st.sampled_from([0.0, 1.0, 1.0, 0.5, np.nan])
        return draw(hnp.arrays(dt, shape, elements=elements))
    if dt.kind in "iu":
        info = np.iinfo(dt)
        lo = 0 if kind == "mask" else max(int(info.min), -3)
        hi = 1 if kind == "mask" else int(info.max) if draw(RARELY) else 5
        return draw(hnp.arrays(dt, shape, elements=st.integers(lo, hi)))
    return draw(hnp.arrays(dt, shape))


@st.composite
def npz_files(draw) -> dict:
    """The arrays of a bring-your-own file plus how to damage the written bytes."""
    s, t, n = draw(st.integers(0, 12)), draw(st.integers(0, 7)), draw(st.integers(1, 4))
    arrays = {"positions": draw(array_like((s, t, n, 2), "float"))}
    if draw(st.booleans()):
        arrays["mask"] = draw(array_like((s, t, n), "mask"))
    if draw(st.booleans()):
        arrays["velocities"] = draw(array_like((s, t, n, 2), "float"))
    if draw(st.booleans()):
        arrays["edges"] = draw(array_like((s, t, num_edges(n)), "edges"))
    if draw(RARELY):
        arrays = {("Positions" if k == "positions" else k): v for k, v in arrays.items()}  # missing key
    damage = draw(st.sampled_from(["none"] * 6 + ["truncate", "flip", "garbage", "npy", "empty"]))
    return {"arrays": arrays, "damage": damage, "cut": draw(st.floats(0, 1)),
            "frame_rate": draw(st.sampled_from([1.0, 2.5, 1e38]))}


def write_npz(spec: dict, path: Path) -> None:
    np.savez(path, **spec["arrays"])
    raw = path.read_bytes()
    cut = int(spec["cut"] * len(raw))
    if spec["damage"] == "truncate":
        path.write_bytes(raw[:cut])
    elif spec["damage"] == "flip":
        path.write_bytes(raw[:cut] + bytes([raw[cut] ^ 0xFF]) + raw[cut + 1:] if cut < len(raw) else raw)
    elif spec["damage"] == "garbage":
        path.write_bytes(bytes(range(256)) * 3)
    elif spec["damage"] == "empty":
        path.write_bytes(b"")
    elif spec["damage"] == "npy":
        with path.open("wb") as f:
            np.save(f, next(iter(spec["arrays"].values())))


def assert_clean(error: BaseException, *names: str) -> None:
    """The project's own error, naming one of ``names`` (a file, a key)."""
    event("rejected: " + re.sub(r"(/[^/\s]+)+/", "", str(error))[:50])  # --hypothesis-show-statistics
    assert type(error) in (ValueError, ConfigError, FileNotFoundError), f"{type(error).__name__}: {error}"
    assert any(name in str(error) for name in names), f"{error!r} names none of {names}"


@FAST
@given(spec=npz_files())
def test_trajectory_reader_fails_cleanly(spec):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "clips.npz"
        write_npz(spec, path)
        try:
            out = load_trajectories(path, spec["frame_rate"])
        except Exception as e:  # noqa: BLE001 - the property is about which exceptions
            assert_clean(e, str(path))
            return
        s, t, n, d = out["states"].shape
        assert d == 4 and n >= 2 and out["mask"].shape == (s, t, n) and out["mask"].dtype == torch.bool
        assert torch.isfinite(out["states"]).all() and (out["states"][~out["mask"]] == 0).all()
        if "edges" in out:
            assert out["edges"].shape == (s, t - 1, num_edges(n)) and (out["edges"] >= 0).all()
        # ...and the whole DataModule on top of it also fails only cleanly.
        dm = data_module("trajectories", source={"path": str(path), "frame_rate": spec["frame_rate"]},
                         loader={"batch_size": 2, "eval_batch_size": 2})
        try:
            dm.setup()
        except Exception as e:  # noqa: BLE001
            assert_clean(e, str(path), "data.")
            return
        batch = next(iter(dm.train_dataloader()))
        assert torch.isfinite(batch["states"]).all()
        event("accepted: a usable data module")


# ------------------------------------------------------------------------------------------ inD / levelX

FILES = ["00_tracks.csv", "00_tracksMeta.csv", "00_recordingMeta.csv"]
VALUES = st.sampled_from([np.nan, np.inf, -np.inf, "abc", "", " ", 1e308, 1e39, -7, 0.5, 10**15, "1e5", "car"])
OPS = st.one_of(
    st.tuples(st.just("drop"), st.sampled_from(FILES), st.floats(0, 1)),
    st.tuples(st.just("set"), st.sampled_from(FILES), st.floats(0, 1), st.floats(0, 1), VALUES),
    st.tuples(st.just("duplicate"), st.sampled_from(FILES), st.floats(0, 1)),
    st.tuples(st.just("delete"), st.sampled_from(FILES), st.floats(0, 1)),
    st.tuples(st.just("shuffle"), st.sampled_from(FILES), st.integers(0, 2**16)),
    st.tuples(st.just("truncate"), st.sampled_from(FILES), st.floats(0, 1)),
    st.tuples(st.just("garbage"), st.sampled_from(FILES), st.binary(min_size=1, max_size=64)),
    st.tuples(st.just("header_only"), st.sampled_from(FILES)),
    st.tuples(st.just("remove"), st.sampled_from(FILES[1:])),
)


def corrupt(root: Path, op: tuple) -> None:
    kind, name, *args = op
    path = root / name
    if kind == "remove":
        path.unlink(missing_ok=True)
        return
    if not path.exists():
        return
    if kind in ("truncate", "garbage"):
        raw = path.read_bytes()
        path.write_bytes(raw[: int(args[0] * len(raw))] if kind == "truncate" else args[0])
        return
    try:
        df = pd.read_csv(path, dtype=str, keep_default_na=False)
    except (ValueError, OSError):  # already damaged beyond a table: leave it
        return
    if kind == "header_only":
        df = df.iloc[:0]
    elif len(df.columns) and kind == "drop":
        df = df.drop(columns=[df.columns[int(args[0] * (len(df.columns) - 1))]])
    elif len(df) and kind == "set":
        row, col = int(args[0] * (len(df) - 1)), df.columns[int(args[1] * (len(df.columns) - 1))]
        df.loc[df.index[row], col] = str(args[2])
    elif len(df) and kind == "duplicate":
        df = pd.concat([df, df.iloc[[int(args[0] * (len(df) - 1))]]])
    elif len(df) and kind == "delete":
        df = df.drop(index=df.index[int(args[0] * (len(df) - 1))])
    elif kind == "shuffle":
        df = df.sample(frac=1.0, random_state=args[0])
    df.to_csv(path, index=False)


@FAST
@given(ops=st.lists(OPS, min_size=1, max_size=3), seed=st.integers(0, 5))
def test_levelx_reader_fails_cleanly_and_caches_atomically(ops, seed):
    with tempfile.TemporaryDirectory() as tmp:
        root, cache = write_ind_root(Path(tmp) / "inD", num_recordings=1, num_frames=400, num_tracks=5,
                                     num_parked=1, seed=seed), Path(tmp) / "cache"
        for op in ops:
            corrupt(root, op)
        dm = TracksDataModule(source={"_target_": LEVELX_SOURCE, "root": str(root)}, windows={"seq_len": 10},
                              cache_dir=str(cache), split=(1, 1, 1))
        params = dm.tracks().params(10)
        try:
            files = discover_recordings(root)[0]
            blob = dm.tracks().recording(files, params)
        except Exception as e:  # noqa: BLE001 - the property is about which exceptions
            assert_clean(e, *FILES, "data.")
            assert not cache.exists() or not any(p.is_file() for p in cache.rglob("*"))  # no cache, no temp
            return
        cached = list((cache / "levelx").iterdir())
        assert [p.suffix for p in cached] == [".pt"]  # exactly the finished cache file, no temporary one
        again = torch.load(cached[0])
        assert torch.equal(again["states"], blob["states"])
        assert torch.isfinite(blob["states"]).all() and blob["states"].shape[1:] == (10, 4)
        assert int(blob["offsets"][-1]) == blob["states"].shape[0] == blob["mask"].shape[0]
        event("accepted: windows cached")


# ------------------------------------------------------------------------------------------ simulator

COUNT = st.one_of(st.integers(-3, 24), st.integers(1, 24), st.sampled_from([2.5, 3.0, True, "8", None, np.int64(5)]))
REAL = st.one_of(ANY_FLOAT, st.integers(-5, 5), st.sampled_from([1e300, -1e300, True, "0.05", None]))
SEED = st.one_of(st.integers(-(2**70), 2**70), st.sampled_from([1.5, "3", None]))


@FAST
@given(num_samples=COUNT, num_steps=COUNT, push_factor=REAL, radius=REAL, seed=SEED)
def test_simulator_rejects_bad_parameters_by_name(num_samples, num_steps, push_factor, radius, seed):
    try:
        states, edges = simulate_push(num_samples, num_steps, push_factor, radius, seed)
    except Exception as e:  # noqa: BLE001
        assert type(e) is ValueError, f"{type(e).__name__}: {e}"
        assert re.search(r"simulate_push: .*(num_samples|num_steps|push_factor|radius|seed)", str(e)), str(e)
        return
    assert states.shape == (num_samples, num_steps, 3, 4) and edges.shape == (num_samples, num_steps, 6)
    assert torch.isfinite(states).all() and set(edges.unique().tolist()) <= {0, 1}
    event("accepted")


SYNTH = st.fixed_dictionaries({
    "num_train": COUNT, "num_val": st.integers(0, 6), "num_test": st.integers(1, 6),
    "num_steps": st.one_of(st.integers(0, 12), st.integers(6, 12), st.just("x")), "push_factor": REAL, "seed": SEED,
})
PUSH_KEYS = ("num_steps", "push_factor", "seed")  # SYNTH's keys of the simulator's node (data.source)


@FAST
@given(params=SYNTH)
def test_synthetic_data_rejects_bad_parameters_by_key(params):
    with tempfile.TemporaryDirectory() as tmp:
        try:
            source = {k: v for k, v in params.items() if k in PUSH_KEYS}
            sizes = {k: v for k, v in params.items() if k not in PUSH_KEYS}
            dm = data_module("synth", cache_dir=tmp, loader={"batch_size": 4}, source=source, **sizes)
            dm.prepare_data()
        except Exception as e:  # noqa: BLE001
            assert_clean(e, "data.", "push_factor")
            assert not any(p.name.startswith(".") for p in Path(tmp).iterdir())  # no temporary file left
            return
        dm.setup()
        assert len(list(Path(tmp).iterdir())) == 3 and torch.isfinite(dm.datasets["train"].states).all()
        event("accepted")


@FAST
@given(num_train=st.integers(1, 20), fail_at=st.integers(0, 2), written=st.integers(0, 64),
       error=st.sampled_from([OSError(28, "No space left on device"), KeyboardInterrupt()]))
def test_interrupted_cache_write_leaves_no_partial_file(num_train, fail_at, written, error):
    """A save that dies part-way (disk full, Ctrl-C) leaves the finished splits and nothing else; the next
    run regenerates the missing ones and everything loads."""
    with tempfile.TemporaryDirectory() as tmp:
        dm = data_module("synth", num_train=num_train, num_val=3, num_test=2, source={"num_steps": 8}, cache_dir=tmp,
                         loader={"batch_size": 4})
        real_save, calls = torch.save, []

        def dying_save(obj, f, *args, **kwargs):
            calls.append(f)
            if len(calls) - 1 == fail_at:
                f.write(bytes(written))  # a partial write into the temporary file
                raise error
            return real_save(obj, f, *args, **kwargs)

        with mock.patch.object(torch, "save", dying_save), pytest.raises(type(error)):
            dm.prepare_data()
        names = sorted(p.name for p in Path(tmp).iterdir())
        assert len(names) == fail_at and all(n.startswith("synth_") and n.endswith(".pt") for n in names)
        dm.prepare_data()
        dm.setup()
        assert len(list(Path(tmp).iterdir())) == 3 and len(dm.datasets["train"]) == num_train


@st.composite
def zhan_files(draw) -> dict:
    """A Zhan-format npz that may be malformed: wrong key, shape or dtype, NaN/inf, or damaged bytes."""
    shape = draw(st.sampled_from([(4, 50, 22), (4, 50, 22), (3, 6, 22), (4, 50, 20), (4, 1, 22), (4, 50)]))
    return {"key": draw(st.sampled_from(["data", "data", "positions"])), "array": draw(array_like(shape, "float")),
            "damage": draw(st.sampled_from(["none", "none", "cut", "garbage", "npy"]))}


@FAST
@given(spec=zhan_files(), split=st.sampled_from(["train", "test"]))
def test_basketball_reader_fails_cleanly(spec, split):
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        good = np.random.default_rng(0).uniform(0, 50, (6, 50, 22)).astype(np.float32)
        for name in ("train", "test"):
            content = {spec["key"]: spec["array"]} if name == split else {"data": good}
            np.savez(root / f"{name}.npz", **content)
        path = root / f"{split}.npz"
        if spec["damage"] == "cut":
            path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
        elif spec["damage"] == "garbage":
            path.write_bytes(bytes(range(256)) * 3)
        elif spec["damage"] == "npy":
            with path.open("wb") as f:
                np.save(f, spec["array"])
        dm = data_module("basketball", source={"root": str(root)}, cache_dir=str(root / "cache"), val_fraction=0.2)
        try:
            dm.prepare_data()
            dm.setup()
        except (ValueError, FileNotFoundError) as err:
            assert_clean(err, str(path), "data.", "basketball")
        else:
            assert torch.isfinite(dm.datasets["train"].states).all()
