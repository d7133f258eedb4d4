"""NRI's particle systems: the physics, the graphs (static and switching), NRI's files and the data module."""

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from dider.data.clips import ClipsDataModule
from dider.data.readers.nri_files import nri_path, read_nri_split, write_nri_split
from dider.data.simulators.particles import STIFFNESS, _forces, simulate_particles
from dider.graph import edge_index
from dider.validation import settings_problems
from helpers.data import data_module
from helpers.protocol import fits

NRI_FILES = "dider.data.readers.nri_files.NRIFiles"
SIMULATION = "dider.data.simulators.particles.Simulation"

SMALL = dict(loader={"batch_size": 4, "eval_batch_size": 4})


def test_forces_by_hand():
    x = torch.tensor([[[0.0, 0.0], [2.0, 0.0], [0.0, 1.0]]], dtype=torch.float64)  # [1, 3, 2]
    e = torch.zeros(1, 3, 3, dtype=torch.float64)
    e[0, 0, 1] = e[0, 1, 0] = 1.0  # a spring between balls 0 and 1 only
    f = _forces("springs", x, e)
    torch.testing.assert_close(f[0], torch.tensor([[2 * STIFFNESS, 0], [-2 * STIFFNESS, 0], [0, 0]],
                                                  dtype=torch.float64))
    q = torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)
    charges = (q[:, None] * q[None]) * (1 - torch.eye(3, dtype=torch.float64))
    f = _forces("charged", x, charges[None])
    # ball 0: repelled by ball 1 (distance 2: 1/4 along -x), attracted by ball 2 (distance 1: 1 along +y)
    torch.testing.assert_close(f[0, 0], torch.tensor([-0.25, 1.0], dtype=torch.float64))


def test_springs_conserve_energy_and_keep_a_static_symmetric_graph():
    loc, vel, edges = simulate_particles("springs", 64, num_frames=30, seed=3)
    assert loc.shape == vel.shape == (64, 30, 2, 5) and edges.shape == (64, 30, 5, 5)
    assert (edges == edges[:, :1]).all() and (edges == edges.transpose(-1, -2)).all()
    assert (edges.diagonal(dim1=-2, dim2=-1) == 0).all() and set(edges.unique().tolist()) == {0, 1}
    x = loc.transpose(2, 3)  # [S, T, N, 2]
    d2 = (x[:, :, :, None] - x[:, :, None]).square().sum(-1)  # [S, T, N, N]
    energy = 0.5 * vel.square().sum((2, 3)) + 0.25 * STIFFNESS * (edges * d2).sum((2, 3))
    drift = (energy - energy[:, :1]).abs().max() / energy.mean()
    assert drift < 0.02, drift  # symplectic Euler at dt = 1e-3, elastic walls: no force is clipped here
    assert loc.abs().max() <= 5.0


def test_charged_labels_come_from_charges():
    _, _, edges = simulate_particles("charged", 40, num_frames=5, seed=1)
    # label[i, j] = 1 exactly when balls i and j carry the same charge: a two-colouring of the balls
    same = edges[:, 0] + torch.eye(5, dtype=torch.long)
    colour = same[:, 0]  # the balls charged like ball 0
    assert (same == (colour[:, :, None] == colour[:, None, :]).long()).all()


def test_switching_graphs_switch_at_the_rate_asked():
    _, _, edges = simulate_particles("springs", 400, num_frames=40, switch_prob=0.05, seed=2)
    upper = torch.triu(torch.ones(5, 5, dtype=torch.bool), 1)
    flips = (edges[:, 1:] != edges[:, :-1])[..., upper].float()
    assert abs(flips.mean().item() - 0.05) < 0.006, flips.mean()
    assert abs(edges[..., upper].float().mean().item() - 0.5) < 0.03
    _, _, charged = simulate_particles("charged", 200, num_frames=40, switch_prob=0.05, seed=2)
    assert (charged[:, 1:] != charged[:, :-1]).any() and (charged == charged.transpose(-1, -2)).all()


def test_simulation_is_seeded_and_checks_its_arguments():
    a, b = simulate_particles("springs", 3, 5, seed=7), simulate_particles("springs", 3, 5, seed=7)
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    assert not torch.equal(a[0], simulate_particles("springs", 3, 5, seed=8)[0])
    for kw, name in (({"system": "gravity"}, "system"), ({"num_balls": 1}, "num_balls"),
                     ({"switch_prob": 1.5}, "switch_prob"), ({"num_frames": 2.0}, "num_frames")):
        with pytest.raises(ValueError, match=name):
            simulate_particles(**{"system": "springs", "num_samples": 2, **kw})


def write_sim(root: Path, sizes=(6, 3, 4), frames: int = 20, switch_prob: float = 0.0) -> dict:
    out = {}
    for i, (split, n) in enumerate(zip(("train", "val", "test"), sizes, strict=True)):
        loc, vel, edges = simulate_particles("springs", n, frames, num_balls=4, switch_prob=switch_prob, seed=i)
        edges = edges if switch_prob else edges[:, 0]  # NRI's static layout [S, N, N]
        write_nri_split(root, split, "_springs4", loc, vel, edges)
        out[split] = (loc, vel, edges)
    return out


def test_nri_files_read_as_nri_reads_them(tmp_path):
    raw = write_sim(tmp_path)
    assert nri_path(tmp_path, "loc", "val", "_springs4").name == "loc_valid_springs4.npy"
    states, edges = read_nri_split(tmp_path, "train", "_springs4")
    loc, vel, matrix = raw["train"]
    assert states.shape == (6, 20, 4, 4) and edges.shape == (6, 19, 12)
    torch.testing.assert_close(states[..., :2], loc.transpose(2, 3).float())
    torch.testing.assert_close(states[..., 2:], vel.transpose(2, 3).float())
    send, recv = edge_index(4)
    assert torch.equal(edges, matrix[:, recv, send][:, None].expand(6, 19, 12))
    # NRI's charged files hold the charges' products, -1 or +1 (the diagonal too): labels 0 and 1
    np.save(nri_path(tmp_path, "edges", "train", "_springs4"), matrix.numpy() * 2.0 - 1.0)
    assert torch.equal(read_nri_split(tmp_path, "train", "_springs4")[1], edges)
    # a directed matrix: rows receive, as in NRI's code (edges[s, i, j] is the edge j -> i)
    directed = torch.zeros(6, 4, 4)
    directed[:, 2, 0] = 1  # 0 -> 2
    np.save(nri_path(tmp_path, "edges", "train", "_springs4"), directed.numpy())
    labels = read_nri_split(tmp_path, "train", "_springs4")[1]
    assert labels[0, 0].nonzero().flatten().tolist() == [int(((send == 0) & (recv == 2)).nonzero())]


@pytest.mark.parametrize("kind, array, match", [
    ("loc", np.zeros((6, 20, 3, 4)), r"loc_train_springs4.npy: shape \(6, 20, 3, 4\); expected \[S, T, 2, N\]"),
    ("vel", np.zeros((6, 20, 2, 3)), r"vel_train_springs4.npy: shape .*expected \(6, 20, 2, 4\)"),
    ("edges", np.zeros((6, 4, 3)), r"edges_train_springs4.npy: shape \(6, 4, 3\); expected \[S, N, N\]"),
    ("edges", np.full((6, 4, 4), -3.0), r"edges_train_springs4.npy: values below -1"),
    ("loc", np.full((6, 20, 2, 4), np.nan), r"loc_train_springs4.npy.*NaN"),
    ("edges", np.array([{"a": 1}], dtype=object), r"edges_train_springs4.npy: not a NumPy .npy array"),
])
def test_bad_nri_files_are_named(tmp_path, kind, array, match):
    write_sim(tmp_path)
    np.save(nri_path(tmp_path, kind, "train", "_springs4"), array, allow_pickle=True)
    with pytest.raises(ValueError, match=match):
        read_nri_split(tmp_path, "train", "_springs4")
    nri_path(tmp_path, kind, "train", "_springs4").unlink()
    with pytest.raises(FileNotFoundError, match=f"{kind}_train_springs4.npy: missing"):
        read_nri_split(tmp_path, "train", "_springs4")


def test_the_data_module_reads_files_as_it_simulates(tmp_path):
    """data=springs and data=nri_files on the files of the same simulation give the same batches."""
    sim = {"system": "springs", "num_balls": 4, "num_frames": 20, "switch_prob": 0.1, "seed": 2}
    made = data_module("springs", source=sim, num_train=6, num_val=3, num_test=4, cache_dir=str(tmp_path / "cache"),
                       **SMALL)
    made.setup()
    files = tmp_path / "files"
    for i, split in enumerate(("train", "val", "test")):
        loc, vel, edges = simulate_particles("springs", (6, 3, 4)[i], 20, 4, switch_prob=0.1, seed=2000 + i)
        write_nri_split(files, split, "_s", loc, vel, edges)
    read = data_module("nri_files", source={"root": str(files), "suffix": "_s"}, **SMALL)
    read.setup()
    for split in ("train", "val", "test"):
        a, b = made.datasets[split], read.datasets[split]
        assert torch.equal(a.states, b.states) and torch.equal(a.edges, b.edges) and a.mask.all()
    assert made.datasets["train"].edges.shape == (6, 19, 12) and (made.datasets["train"].edges.diff(dim=1) != 0).any()
    x = made.datasets["train"].states
    assert x[..., :2].min() == -1 and x[..., :2].max() == 1 and x[..., 2:].min() == -1  # NRI's normalisation


def test_the_data_module_names_bad_settings(tmp_path, make_cfg):
    with pytest.raises(ValueError, match=r"data.source.root: no such setting \(expected one of \['system'"):
        ClipsDataModule(source={"_target_": SIMULATION, "root": str(tmp_path)}, num_train=2, num_val=2, num_test=2)
    with pytest.raises(ValueError, match=r"data.source._target_='dider.data.readers.nri': no such class \(module "
                       r"'dider.data.readers' has no 'nri'\)"):
        ClipsDataModule(source={"_target_": "dider.data.readers.nri"})
    with pytest.raises(ValueError, match=r"data.source._target_: not set; name the clip source's class \(dider's: "
                       r"dider.data.readers.basketball.BasketballFiles, .*, dider.data.simulators.push.Push; or"):
        ClipsDataModule(source={"reader": "nri_files"})  # no _target_: a name picks no class
    with pytest.raises(ValueError, match=r"data.source._target_='dider.data.track_sources.TableFile': not a clip "
                       r"source \(missing \['clips'\]\)"):
        ClipsDataModule(source={"_target_": "dider.data.track_sources.TableFile"})
    with pytest.raises(ValueError, match="data.num_train=None: must be an integer"):
        ClipsDataModule(source={"_target_": SIMULATION})
    with pytest.raises(ValueError, match="data.source.system='gravity'"):
        data_module("springs", source={"system": "gravity"}, num_train=2, num_val=2, num_test=2)
    names = "['system', 'num_balls', 'num_frames', 'sample_every', 'switch_prob', 'seed']"
    cfg = make_cfg(["data=springs", "+data.source.frames=3"])  # the preflight's message, before anything is built
    assert settings_problems(OmegaConf.to_container(cfg.data), "data") == [
        f"data.source.frames: no such setting (expected one of {names})"]
    with pytest.raises(Exception, match=r"unexpected keyword argument 'frames'(.|\n)*full_key: data.source"):
        instantiate(cfg.data)
    with pytest.raises(ValueError, match="data.source.root is not set"):
        ClipsDataModule(source={"_target_": NRI_FILES}, **SMALL).setup()
    write_sim(tmp_path / "f", frames=12)
    dm = data_module("nri_files", source={"root": str(tmp_path / "f"), "suffix": "_springs4"}, **SMALL)
    dm.setup()
    with pytest.raises(ValueError, match=r"protocol.horizons=\[1, 10\]: each must lie in 1..2 .*12-step clips, "
                                         r"the test"):
        fits(dm, 10, (1, 10))
