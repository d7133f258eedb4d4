"""The data caches' file names, pinned: a rewrite of the data layer that changes what a key hashes (a renamed
field, a new default in the dict) would rebuild every user's cache without a word, or worse, read a stale one."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

import dider.data.cache as cache
from dider.data.levelx.reading import WindowParams
from dider.data.simulators import push as push_simulator
from dider.data.tracks import TracksDataModule
from helpers.data import data_module

LEVELX_SOURCE = "dider.data.levelx.source.LevelXSource"

PUSH = {  # data=synth at its defaults, and with the positive control's step push
    "linear": {"train": "665bdfec1ceb0ee4", "val": "31036e376cd5978b", "test": "cc0f6d3fe258aad6"},
    "step": {"train": "ba2d230c4b8726eb", "val": "56daa92819c093fa", "test": "781b7bb1c219e356"},
}


@pytest.mark.parametrize("push", sorted(PUSH))
def test_the_push_simulators_cache_names(tmp_path, push):
    dm = data_module("synth", cache_dir=str(tmp_path), source={"push": push})
    sizes = {s: dm.hparams[f"num_{s}"] for s in PUSH[push]}
    names = {s: push_simulator.cache_path(dm.source, s, n, dm.cache_dir).name for s, n in sizes.items()}
    assert names == {s: f"synth_{s}_{k}.pt" for s, k in PUSH[push].items()}


@pytest.mark.parametrize("simulate, name", [
    ({"system": "springs"}, "springs_train_cd386de7999a3d82.pt"),
    ({"system": "charged", "switch_prob": 0.1}, "charged_train_6dfa6dc51f596376.pt"),
])
def test_the_particle_simulators_cache_names(tmp_path, monkeypatch, simulate, name):
    seen: list[Path] = []

    def record(path: Path, build):
        seen.append(path)
        raise LookupError  # stop before simulating

    monkeypatch.setattr(cache, "load_or_build", record)
    dm = data_module("springs", source=simulate, num_train=50000, num_val=10000, num_test=10000,
                     cache_dir=str(tmp_path))
    with pytest.raises(LookupError):
        dm.prepare_data()
    assert [p.name for p in seen] == [name]


def test_a_levelx_recordings_cache_name(tmp_path):
    files = SimpleNamespace(id="00", signature=lambda: [
        ("00_tracks.csv", 100, 5), ("00_tracksMeta.csv", 10, 5), ("00_recordingMeta.csv", 1, 5)])
    dm = TracksDataModule(source={"_target_": LEVELX_SOURCE, "root": str(tmp_path)}, cache_dir=str(tmp_path))
    assert dm.tracks().cache_path(files, WindowParams()).name == "ind_00_acc2bd9a07cc918a.pt"
