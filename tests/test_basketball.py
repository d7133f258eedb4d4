"""Basketball reader: Zhan et al. npz and DNRI npy formats, DNRI's 5-offence / 49-step setting, errors."""

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from dider.data.clips import ClipsDataModule
from dider.data.readers.basketball import detect_format
from helpers.data import data_module
from helpers.fixtures import write_dnri_bball, write_zhan
from helpers.protocol import fits


def make_dm(root: Path | None, source: dict | None = None, **kw) -> ClipsDataModule:
    """data=basketball on the files in ``root``, ``source`` over its source's settings, ``kw`` over the module's."""
    source = {"root": None if root is None else str(root), **(source or {})}
    dm = data_module("basketball", source=source, **{"loader": {"batch_size": 8}, **kw})
    dm.prepare_data()
    dm.setup()
    return dm


def raw(dm: ClipsDataModule, split: str) -> torch.Tensor:
    return dm.normalizer.denormalize(dm.datasets[split].states)


def test_zhan_format_dnri_setting(tmp_path):
    files = write_zhan(tmp_path)
    dm = make_dm(tmp_path)
    assert detect_format(tmp_path) == "zhan" and dm.units == "ft"
    assert dm.clip_steps() == {"train": 49, "val": 49, "test": 49}
    fits(dm, 40, (1, 5, 9))  # DNRI's protocol: 40 observed, 9 forecast
    assert {s: len(d) for s, d in dm.datasets.items()} == {"train": 36, "val": 4, "test": 12}
    batch = next(iter(dm.train_dataloader()))
    assert set(batch) == {"states", "mask", "everyone"} and batch["everyone"]
    assert batch["states"].shape == (8, 49, 5, 4) and batch["mask"].all()
    # test clip = offence columns 2..11 from step 1 on, velocity = finite difference * 6.25 (feet / s)
    data = torch.as_tensor(files["test.npz"], dtype=torch.float32)
    pos = data[:, :, 2:12].reshape(12, 50, 5, 2)
    torch.testing.assert_close(raw(dm, "test")[..., :2], pos[:, 1:], atol=1e-3, rtol=0)
    torch.testing.assert_close(raw(dm, "test")[..., 2:], (pos[:, 1:] - pos[:, :-1]) * 6.25, atol=1e-3, rtol=0)
    tr = dm.datasets["train"].states
    assert tr.min() == pytest.approx(-1, abs=1e-5) and tr.max() == pytest.approx(1, abs=1e-5)


def test_validation_carved_reproducibly(tmp_path):
    files = write_zhan(tmp_path)
    a, b = make_dm(tmp_path), make_dm(tmp_path)
    assert torch.equal(a.datasets["val"].states, b.datasets["val"].states)
    c = make_dm(tmp_path, seed=2, val_fraction=0.25)
    assert len(c.datasets["val"]) == 10
    assert not torch.equal(c.datasets["val"].states[:4], a.datasets["val"].states)
    # train and val partition the training file
    pos = torch.as_tensor(files["train.npz"], dtype=torch.float32)[:, 1:, 2:12].reshape(40, 49, 5, 2)
    both = torch.cat([raw(a, "train"), raw(a, "val")])[..., :2]
    assert both.shape[0] == 40
    dist = (both[:, None] - pos[None]).abs().amax(dim=(2, 3, 4))  # [40, 40]
    assert (dist.min(1).values < 1e-3).all() and (dist.min(0).values < 1e-3).all()


def test_agents_options_alt_names_caps_and_train_len(tmp_path):
    write_zhan(tmp_path, names=("bball_train.npz", "bball_test.npz"))
    dm = make_dm(tmp_path, source={"agents": "all"}, num_train=10, num_test=5, train_len=40)
    assert dm.datasets["test"].states.shape == (5, 49, 11, 4) and len(dm.datasets["train"]) == 10
    assert dm.datasets["train"].states.shape[1] == 40
    assert make_dm(tmp_path, source={"agents": "defence"}).datasets["val"].states.shape[2] == 5


def test_dnri_format(tmp_path):
    arrays = write_dnri_bball(tmp_path)
    dm = make_dm(tmp_path)
    assert detect_format(tmp_path) == "dnri"
    assert {s: len(d) for s, d in dm.datasets.items()} == {"train": 30, "val": 8, "test": 10}
    loc, vel = arrays["valid"]
    want = torch.as_tensor(np.concatenate([loc, vel], -1), dtype=torch.float32)
    torch.testing.assert_close(raw(dm, "val"), want, atol=1e-3, rtol=0)
    # without the valid files the validation split is carved from train
    for kind in ("loc", "vel"):
        (tmp_path / f"{kind}_valid_bball.npy").unlink()
    dm = make_dm(tmp_path, val_fraction=0.2)
    assert {s: len(d) for s, d in dm.datasets.items()} == {"train": 24, "val": 6, "test": 10}


def test_hydra_config_instantiates(tmp_path, make_cfg):
    write_zhan(tmp_path / "bb")
    cfg = make_cfg(["data=basketball", f"data.source.root={tmp_path / 'bb'}"])
    dm = instantiate(cfg.data, _convert_="all")
    dm.setup()
    assert next(iter(dm.test_dataloader()))["states"].shape[1:] == (49, 5, 4)
    assert cfg.model.protocol.burn_in == 40 and list(cfg.model.protocol.horizons) == [1, 5, 9]


def _write_npz(path, **arrays):
    np.savez(path, **arrays)


def test_bad_input(tmp_path):
    with pytest.raises(ValueError, match="data.source.root is not set"):
        make_dm(None)
    with pytest.raises(FileNotFoundError, match="no such folder"):
        make_dm(tmp_path / "nowhere")
    with pytest.raises(FileNotFoundError, match="no basketball data found"):
        make_dm(tmp_path)
    write_zhan(tmp_path)
    _write_npz(tmp_path / "test.npz", frames=np.zeros((4, 50, 22)))
    with pytest.raises(ValueError, match=r"test.npz: no key 'data'"):
        make_dm(tmp_path)
    _write_npz(tmp_path / "test.npz", data=np.zeros((4, 50, 20)))
    with pytest.raises(ValueError, match=r"test.npz: key 'data' has shape \(4, 50, 20\)"):
        make_dm(tmp_path)
    bad = np.zeros((4, 50, 22))
    bad[1, 3, 5] = np.nan
    _write_npz(tmp_path / "test.npz", data=bad)
    with pytest.raises(ValueError, match=r"test.npz: key 'data': 1 NaN/inf"):
        make_dm(tmp_path)
    _write_npz(tmp_path / "test.npz", data=np.zeros((4, 30, 22)))  # 29 steps < 40 burn-in
    with pytest.raises(ValueError, match=r"protocol.burn_in=40 must be shorter than the clips \(29 steps, the test"):
        fits(make_dm(tmp_path), 40, (1, 5, 9))
    _write_npz(tmp_path / "test.npz", data=np.zeros((4, 47, 22)))  # 46 steps: horizon 9 needs 49
    with pytest.raises(ValueError, match=r"protocol.horizons=\[1, 5, 9\]: each must lie in 1..6"):
        fits(make_dm(tmp_path), 40, (1, 5, 9))
    fits(make_dm(tmp_path, train_len=40), 40, (1, 5, 6), stage="fit")  # training crops may be as short as the burn-in
    write_dnri_bball(tmp_path)
    with pytest.raises(ValueError, match="both Zhan npz and DNRI npy"):
        make_dm(tmp_path)
    np.save(tmp_path / "vel_test_bball.npy", np.zeros((10, 48, 5, 2)))
    with pytest.raises(ValueError, match=r"vel_test_bball.npy: shape \(10, 48, 5, 2\) differs"):
        make_dm(tmp_path, source={"format": "dnri"})
    np.save(tmp_path / "vel_test_bball.npy", np.zeros((10, 49, 10)))
    with pytest.raises(ValueError, match=r"vel_test_bball.npy: shape \(10, 49, 10\); expected \[S, T, N, 2"):
        make_dm(tmp_path, source={"format": "dnri"})
    (tmp_path / "vel_test_bball.npy").unlink()
    with pytest.raises(FileNotFoundError, match="vel_test_bball.npy: missing"):
        make_dm(tmp_path, source={"format": "dnri"})
    assert detect_format(tmp_path) == "zhan"


BAD_CONFIG = [({"source": {"format": "csv"}}, "data.source.format"),
              ({"source": {"agents": "ball"}}, "data.source.agents"),
              ({"val_fraction": 1.0}, "data.val_fraction"), ({"train_len": 1}, "data.train_len")]


@pytest.mark.parametrize("kw, key", BAD_CONFIG)
def test_bad_config_names_the_key(kw, key):
    with pytest.raises(ValueError, match=key):
        data_module("basketball", **kw)
