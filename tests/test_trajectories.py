"""Bring-your-own trajectories npz: velocities, masks, edge alignment, seeded splits, errors."""

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from dider.data.clip_splits import split_indices
from dider.data.clips import ClipsDataModule
from dider.run import train
from helpers.data import data_module
from helpers.fixtures import write_trajectories
from helpers.protocol import fits


def make_dm(path: Path | None, source: dict | None = None, **kw) -> ClipsDataModule:
    """data=trajectories on the file ``path``, ``source`` over its source's settings, ``kw`` over the module's."""
    source = {"path": None if path is None else str(path), **(source or {})}
    dm = data_module("trajectories", source=source, **{"loader": {"batch_size": 8}, **kw})
    dm.setup()
    return dm


def all_clips(dm: ClipsDataModule) -> dict[str, torch.Tensor]:
    """States of every split in the file's coordinates, put back in file order: [S, T, N, 4] (and masks)."""
    parts = split_indices(sum(len(d) for d in dm.datasets.values()), dm.hparams.split, dm.hparams.seed)
    n = sum(len(v) for v in parts.values())
    ds = dm.datasets["train"]
    states = torch.zeros(n, *ds.states.shape[1:])
    mask = torch.zeros(n, *ds.mask.shape[1:], dtype=torch.bool)
    for split, idx in parts.items():
        states[idx] = dm.normalizer.to_user(dm.normalizer.denormalize(dm.datasets[split].states)).float()
        mask[idx] = dm.datasets[split].mask
    return {"states": states, "mask": mask}


def test_positions_only_finite_difference(tmp_path):
    arrays = write_trajectories(tmp_path / "t.npz")
    dm = make_dm(tmp_path / "t.npz", source={"frame_rate": 2.0})
    assert {s: len(d) for s, d in dm.datasets.items()} == {"train": 32, "val": 4, "test": 4}
    batch = next(iter(dm.train_dataloader()))
    assert set(batch) == {"states", "mask", "source", "everyone"} and batch["everyone"]
    assert batch["states"].shape == (8, 19, 3, 4) and batch["mask"].all()
    # each clip's source: its index in the file, and the file's step 0 is frame 1 (differencing used frame 0)
    test_idx = split_indices(40, dm.hparams.split, dm.hparams.seed)["test"]
    test_batch = next(iter(dm.test_dataloader()))
    assert test_batch["source"]["clip"].tolist() == test_idx.tolist()
    assert (test_batch["source"]["frame"] == 1).all()
    torch.testing.assert_close(dm.normalizer.to_user(dm.normalizer.denormalize(test_batch["states"]))[..., :2].float(),
                               torch.as_tensor(arrays["positions"], dtype=torch.float32)[test_idx, 1:], atol=1e-4,
                               rtol=0)
    pos = torch.as_tensor(arrays["positions"], dtype=torch.float32)
    got = all_clips(dm)["states"]
    torch.testing.assert_close(got[..., :2], pos[:, 1:], atol=1e-4, rtol=0)
    torch.testing.assert_close(got[..., 2:], (pos[:, 1:] - pos[:, :-1]) * 2.0, atol=1e-4, rtol=0)
    tr = dm.datasets["train"].states
    assert tr.min() == pytest.approx(-1, abs=1e-5) and tr.max() == pytest.approx(1, abs=1e-5)


def test_given_velocities_keep_every_step(tmp_path):
    arrays = write_trajectories(tmp_path / "t.npz", velocities=True)
    dm = make_dm(tmp_path / "t.npz")
    got = all_clips(dm)["states"]
    want = np.concatenate([arrays["positions"], arrays["velocities"]], -1)
    want = torch.as_tensor(want, dtype=torch.float32)
    torch.testing.assert_close(got, want, atol=1e-4, rtol=0)


@pytest.mark.parametrize("velocities", [True, False])
def test_mask_and_edges_alignment(tmp_path, velocities):
    arrays = write_trajectories(tmp_path / "t.npz", velocities=velocities, mask=True, edges=True)
    dm = make_dm(tmp_path / "t.npz")
    drop = 0 if velocities else 1
    t = 20 - drop
    batch = next(iter(dm.test_dataloader()))
    assert batch["states"].shape[1] == t
    assert batch["edges"].shape == (4, t - 1, 6) and batch["edges"].dtype == torch.long
    assert torch.isfinite(batch["states"]).all() and (batch["states"][~batch["mask"]] == 0).all()
    # the last agent leaves at step 10 of the file; a differenced velocity also needs step t-1
    m = torch.as_tensor(arrays["mask"])
    want_mask = m if velocities else m[:, 1:] & m[:, :-1]
    assert torch.equal(all_clips(dm)["mask"], want_mask)
    # edges[:, t] produced file step t from t-1: the clip's transition j -> j+1 is file edges[drop + j + 1]
    test_idx = split_indices(40, dm.hparams.split, dm.hparams.seed)["test"]
    raw_edges = torch.as_tensor(arrays["edges"])
    assert torch.equal(dm.datasets["test"].edges, raw_edges[test_idx, drop + 1:])


def test_split_is_seeded_and_caps(tmp_path):
    write_trajectories(tmp_path / "t.npz")
    a, b = make_dm(tmp_path / "t.npz"), make_dm(tmp_path / "t.npz")
    assert torch.equal(a.datasets["test"].states, b.datasets["test"].states)
    c = make_dm(tmp_path / "t.npz", seed=5, split=(0.5, 0.25, 0.25), num_train=6)
    assert {s: len(d) for s, d in c.datasets.items()} == {"train": 6, "val": 10, "test": 10}
    parts = split_indices(40, (0.8, 0.1, 0.1), 1)
    assert sorted(torch.cat(list(parts.values())).tolist()) == list(range(40))


def test_hydra_config_instantiates(tmp_path, make_cfg):
    write_trajectories(tmp_path / "t.npz", edges=True)
    cfg = make_cfg(["data=trajectories", f"data.source.path={tmp_path / 't.npz'}"])
    dm = instantiate(cfg.data, _convert_="all")
    dm.setup()
    assert "edges" in next(iter(dm.val_dataloader()))


def test_bad_input(tmp_path):
    p = tmp_path / "t.npz"
    with pytest.raises(ValueError, match="data.source.path is not set"):
        make_dm(None)
    with pytest.raises(FileNotFoundError, match="no such file"):
        make_dm(p)
    p.write_text("not an npz")
    with pytest.raises(ValueError, match="not a readable .npz"):
        make_dm(p)
    pos = np.zeros((4, 20, 3, 2))
    cases = [
        ({"pos": np.zeros((4, 20, 3))}, r"no key 'positions'"),
        ({"positions": np.zeros((4, 20, 3))}, r"key 'positions' has shape \(4, 20, 3\)"),
        ({"positions": pos, "velocities": np.zeros((4, 20, 3, 3))}, r"key 'velocities' has shape"),
        ({"positions": pos, "mask": np.ones((4, 20, 2), bool)}, r"key 'mask' has shape"),
        ({"positions": pos, "mask": np.full((4, 20, 3), 2)}, r"key 'mask' must be bool"),
        ({"positions": pos, "edges": np.zeros((4, 20, 9), int)}, r"key 'edges' has shape"),
        ({"positions": pos, "edges": np.full((4, 20, 6), 0.5)}, r"key 'edges' must hold integer"),
        ({"positions": pos, "edges": np.full((4, 20, 6), -1)}, r"negative edge types"),
        ({"positions": np.full((4, 20, 3, 2), np.nan)}, r"key 'positions' \(mark absent agents with a"),
        ({"positions": np.zeros((4, 1, 3, 2))}, r"finite-difference velocities need >= 2"),
        ({"positions": np.zeros((2, 20, 3, 2))}, r"too few for train, val and test"),
    ]
    for arrays, match in cases:
        np.savez(p, **arrays)
        with pytest.raises(ValueError, match=match):
            make_dm(p)
    arrays = write_trajectories(p, mask=True)
    arrays["positions"][0, 0, 0] = np.nan  # present agent: an error even with a mask
    np.savez(p, **arrays)
    with pytest.raises(ValueError, match=r"key 'positions': 2 NaN/inf values \(first at index \(0, 0, 0, 0"):
        make_dm(p)
    write_trajectories(p, num=10, steps=12)  # 11 steps once differenced: horizon 10 needs 15
    with pytest.raises(ValueError, match=r"protocol.horizons=\[1, 5, 10\]: each must lie in 1..6 \(the predicted steps "
                                         r"after protocol.burn_in=5 of 11-step clips, the test split's\)"):
        fits(make_dm(p), 5, (1, 5, 10))
    with pytest.raises(ValueError, match=r"protocol.burn_in=11 must be shorter "):
        fits(make_dm(p), 11, (1,), stage="fit")


@pytest.mark.parametrize("kw, key", [({"split": (0.5, 0.5)}, "data.split"),
                                     ({"source": {"frame_rate": 0}}, "data.source.frame_rate"),
                                     ({"loader": {"batch_size": 0}}, "data.loader.batch_size")])
def test_bad_config_names_the_key(kw, key):
    with pytest.raises(ValueError, match=key):
        data_module("trajectories", **kw)


def test_a_run_checks_the_protocol_against_the_clips_before_training(make_cfg, tmp_path):
    """The clip length of a file is known once it is read: the run stops there, naming the model's key and the
    protocol's, before any training step."""
    write_trajectories(tmp_path / "short.npz", num=10, steps=9)  # 8 steps once differenced
    cfg = make_cfg(["data=trajectories", f"data.source.path={tmp_path / 'short.npz'}",
                   "logger=none"], out=tmp_path / "run")
    with pytest.raises(ValueError, match=r"protocol.horizons=\[1, 5, 10\]: each must lie in 1..3 .*the val split's\)$"):
        train(cfg)
    assert not list((tmp_path / "run").rglob("*.ckpt"))
