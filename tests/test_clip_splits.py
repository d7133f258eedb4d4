"""Clip sources and the one path from their splits to datasets: selection, crops, caps, normalisation, ids."""

from __future__ import annotations

import pytest
import torch

from dider.data.batch import Normalizer
from dider.data.clip_source import Clips
from dider.data.clip_splits import capped, clip_datasets
from dider.data.readers import dnri_files, nri_files, trajectories
from helpers.fixtures import write_trajectories
from test_dnri_files import write_dnri


def clips(count: int = 5, steps: int = 4, agents: int = 3) -> Clips:
    states = torch.arange(count * steps * agents * 4, dtype=torch.float32).reshape(count, steps, agents, 4)
    mask = torch.ones(count, steps, agents, dtype=torch.bool)
    mask[:, :, 2] = torch.arange(steps) < 2  # agent 2 leaves after step 1
    edges = torch.arange(count * (steps - 1) * 6).reshape(count, steps - 1, 6)
    return Clips(states, mask, edges, {"clip": torch.arange(count) + 10, "agent": torch.arange(count * 3).view(-1, 3)})


def test_select_and_crop_keep_every_field_aligned() -> None:
    c = clips()
    s = c.select(torch.tensor([3, 1]))
    assert torch.equal(s.states[0], c.states[3]) and torch.equal(s.mask[1], c.mask[1])
    assert torch.equal(s.edges[0], c.edges[3]) and s.ids["clip"].tolist() == [13, 11]
    assert s.ids["agent"].tolist() == [[9, 10, 11], [3, 4, 5]]
    k = c.crop(2)
    assert k.states.shape[1] == 2 and k.mask.shape[1] == 2 and k.edges.shape[1] == 1 and k.ids is c.ids
    assert Clips(c.states).present.all() and Clips(c.states).crop(3).edges is None


def test_caps_spread_over_each_split_and_leave_uncapped_splits_whole() -> None:
    parts = capped({"train": clips(5), "test": clips(3)}, {"train": 3, "test": None})
    assert parts["train"].ids["clip"].tolist() == [10, 12, 14]  # evenly spread, not the first three
    assert parts["test"].ids["clip"].tolist() == [10, 11, 12]


def test_datasets_are_normalised_with_absent_agents_at_zero() -> None:
    c = clips(2)
    norm = Normalizer((0.0, 10.0), (-5.0, 5.0))
    ds = clip_datasets({"val": c}, norm)["val"]
    x = c.states[0, 0, 0]  # present: hand-computed map to [-1, 1] by the ranges
    want = torch.tensor([x[0] / 5 - 1, x[1] / 5 - 1, (x[2] + 5) / 5 - 1, (x[3] + 5) / 5 - 1])
    assert torch.allclose(ds.states[0, 0, 0], want)
    assert (ds.states[:, 2:, 2] == 0).all() and not ds.everyone  # absent after step 1: zeros
    assert torch.equal(ds.edges, c.edges) and ds.sources["clip"].tolist() == [10, 11]
    full = clip_datasets({"train": Clips(c.states)}, norm)["train"]
    assert full.everyone and full.sources is None and full.edges is None


def test_file_readers_give_clips_with_their_indices(tmp_path) -> None:
    write_dnri(tmp_path / "dnri", steps=12)
    parts = dnri_files.read(tmp_path / "dnri")
    feats, edges = dnri_files.load_split(tmp_path / "dnri", "val")
    assert torch.equal(parts["val"].states, feats) and torch.equal(parts["val"].edges, edges[:, 1:])
    assert parts["val"].ids["clip"].tolist() == list(range(len(feats)))
    path = tmp_path / "traj.npz"
    write_trajectories(path, num=6, steps=8, agents=3, mask=True, edges=True)
    c = trajectories.read(path, frame_rate=2.0)
    assert len(c) == 6 and c.ids["frame"].tolist() == [1] * 6  # differenced velocities: step 0 is the file's 1
    with pytest.raises(ValueError, match="data.source.path is not set"):
        trajectories.read(None)
    with pytest.raises(FileNotFoundError, match="no such file"):
        trajectories.read(tmp_path / "none.npz")
    with pytest.raises(ValueError, match="data.source.root is not set"):
        nri_files.read(None, "_springs5")
