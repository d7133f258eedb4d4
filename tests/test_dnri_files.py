"""The DNRI code's synthetic files (data=dnri_files): layout, edge alignment, normalisation, predict, errors."""

from pathlib import Path

import pytest
import torch
from hydra.utils import instantiate

from dider.data.batch import Normalizer
from dider.data.clips import ClipsDataModule
from dider.data.simulators.push import EDGE_0_TO_2, EDGE_1_TO_2, simulate_push
from helpers.data import data_module

SIZES = {"train": 8, "val": 3, "test": 5}
STEPS = 30
SMALL = dict(loader={"batch_size": 4, "eval_batch_size": 4})


def write_dnri(root: Path, sizes: dict[str, int] = SIZES, steps: int = STEPS) -> dict[str, tuple]:
    """The six files as the DNRI generator writes them: float feats [S, T, 3, 4] and float 0/1 edges [S, T, 6]
    (edges[:, t] produced step t from t-1, which our simulator shares with it)."""
    root.mkdir(parents=True, exist_ok=True)
    out = {}
    for i, (split, num) in enumerate(sizes.items()):
        feats, edges = simulate_push(num, steps, push_factor=0.05, seed=10 + i)
        torch.save(feats, root / f"{split}_feats")
        torch.save(edges.float(), root / f"{split}_edges")
        out[split] = (feats, edges)
    return out


@pytest.fixture
def root(tmp_path: Path) -> Path:
    return tmp_path / "dnri"


def make_dm(root: Path | None, setup: bool = True, source: dict | None = None, **kw) -> ClipsDataModule:
    """data=dnri_files on the files in ``root``, ``source`` over its source's settings, ``kw`` over the module's."""
    source = {"root": None if root is None else str(root), **(source or {})}
    dm = data_module("dnri_files", source=source, **{**SMALL, **kw})
    if setup:
        dm.setup()
    return dm


def test_layout_and_edge_alignment(root):
    raw = write_dnri(root)
    dm = make_dm(root)
    assert {s: len(d) for s, d in dm.datasets.items()} == SIZES
    batch = next(iter(dm.val_dataloader()))
    assert batch["states"].shape == (3, STEPS, 3, 4) and batch["mask"].all()
    assert batch["edges"].shape == (3, STEPS - 1, 6) and batch["edges"].dtype == torch.long
    assert batch["source"]["clip"].tolist() == [0, 1, 2]
    feats, edges = raw["test"]
    ds = dm.datasets["test"]
    assert torch.equal(ds.edges, edges[:, 1:])  # raw edges[:, t] produced step t: transition t -> t+1 is t+1
    # Physical check: particle 2's velocity changes over exactly the transitions labelled with a push.
    dv = (feats[:, 1:, 2, 2:] - feats[:, :-1, 2, 2:]).abs().sum(-1) > 0  # [S, T-1]
    pushed = (ds.edges[..., EDGE_0_TO_2] + ds.edges[..., EDGE_1_TO_2]) > 0
    assert pushed.any() and torch.equal(dv, pushed)


def test_normalisation_matches_dnri(root):
    raw = write_dnri(root)
    train = raw["train"][0]
    dm = make_dm(root, num_train=2)  # the ranges still come from the whole train file, as in DNRI
    lo_p, hi_p = train[..., :2].min().item(), train[..., :2].max().item()
    lo_v, hi_v = train[..., 2:].min().item(), train[..., 2:].max().item()
    assert dm.normalizer.pos_range == pytest.approx((lo_p, hi_p)) and len(dm.datasets["train"]) == 2
    assert dm.normalizer.vel_range == pytest.approx((lo_v, hi_v))
    val = raw["val"][0]
    want = torch.cat([(val[..., :2] - lo_p) * 2 / (hi_p - lo_p) - 1, (val[..., 2:] - lo_v) * 2 / (hi_v - lo_v) - 1], -1)
    torch.testing.assert_close(dm.datasets["val"].states, want)
    same = make_dm(root, normalization="same")
    torch.testing.assert_close(same.datasets["val"].states, (val - train.min()) * 2 / (train.max() - train.min()) - 1)
    none = make_dm(root, normalization="none")
    torch.testing.assert_close(none.datasets["val"].states, val)
    assert make_dm(root, num_test=2).datasets["test"].sources["clip"].tolist() == [0, 4]  # spread, file indices


def test_predict_every_clip_with_the_given_normaliser(root):
    raw = write_dnri(root)
    norm = Normalizer((-3.0, 3.0), (-0.2, 0.2))
    for split in ("test", "val"):
        dm = make_dm(root, setup=False, source={"predict_split": split})
        dm.use_normalizer(norm)
        dm.setup("predict")
        ds = dm.datasets["predict"]
        assert ds.sources["clip"].tolist() == list(range(SIZES[split]))
        torch.testing.assert_close(ds.states, norm.normalize(raw[split][0]))
        assert torch.equal(ds.edges, raw[split][1][:, 1:])
    with pytest.raises(ValueError, match="use_normalizer"):
        make_dm(root, setup=False).setup("predict")


class RunsCode:
    """Unpickling this would call open(marker, 'w'): the loader must refuse it without calling anything."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return open, (str(self.marker), "w")


def test_pickles_and_non_tensors_are_refused(root, tmp_path):
    write_dnri(root)
    marker = tmp_path / "ran"
    torch.save(RunsCode(marker), root / "val_feats")
    with pytest.raises(ValueError, match=r"val_feats: refused: the file pickles objects other than tensors"):
        make_dm(root)
    assert not marker.exists()
    torch.save({"feats": torch.zeros(2, 3, 3, 4)}, root / "val_feats")
    with pytest.raises(ValueError, match=r"val_feats: holds a dict, not a tensor"):
        make_dm(root)
    (root / "val_feats").write_text("x,y\n1,2\n")
    with pytest.raises(ValueError, match=r"val_feats: not a tensor file written by torch.save"):
        make_dm(root)


def test_bad_input(root, tmp_path):
    with pytest.raises(ValueError, match="data.source.root is not set"):
        make_dm(None)
    with pytest.raises(FileNotFoundError, match="no such folder"):
        make_dm(tmp_path / "nowhere")
    raw = write_dnri(root)
    (root / "test_edges").unlink()
    with pytest.raises(FileNotFoundError, match=r"test_edges: missing"):
        make_dm(root)
    feats, edges = raw["test"]
    nan = feats.clone()
    nan[1, 2, 0, 3] = float("nan")
    cases = [
        ("feats", feats[..., :3], r"test_feats: shape \(5, 30, 3, 3\); expected \[S, T, N, 4\]"),
        ("feats", feats[:, :, :1], r"test_feats: 1 agent\(s\)"),
        ("feats", nan, r"test_feats: 1 NaN/inf values \(first at index \(1, 2, 0, 3\): NaN\)"),
        ("feats", feats > 0, r"test_feats: dtype torch.bool"),
        ("edges", edges[..., :5], r"test_edges: shape \(5, 30, 5\); expected \[S, T, N\(N-1\)\] = \(5, 30, 6\)"),
        ("edges", edges[:4], r"test_edges: shape \(4, 30, 6\)"),
        ("edges", edges[:, :29], r"test_edges: shape \(5, 29, 6\)"),
        ("edges", edges.float() + 0.5, r"test_edges: edge types must be integers \(first bad value 0.5"),
        ("edges", edges - 1, r"test_edges: edge types must lie in 0"),
    ]
    for kind, value, match in cases:
        write_dnri(root)
        torch.save(value, root / f"test_{kind}")
        with pytest.raises(ValueError, match=match):
            make_dm(root)


@pytest.mark.parametrize("kw, key", [({"normalization": "minmax"}, "data.normalization"),
                                     ({"source": {"predict_split": "all"}}, "data.source.predict_split"),
                                     ({"num_train": 0}, "data.num_train")])
def test_bad_config_names_the_key(kw, key):
    with pytest.raises(ValueError, match=key):
        data_module("dnri_files", **kw)


def test_hydra_config_instantiates(root, make_cfg):
    write_dnri(root)
    cfg = make_cfg(["data=dnri_files", f"data.source.root={root}", "protocol.horizons=[1,10]"])
    dm = instantiate(cfg.data, _convert_="all")
    dm.setup()
    assert dm.hparams.normalization == "separate" and "edges" in next(iter(dm.val_dataloader()))
