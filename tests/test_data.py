import pytest
import torch

from dider.data.batch import Normalizer
from dider.data.clips import ClipsDataModule
from dider.data.simulators.push import simulate_push
from helpers.data import data_module

SIMULATION = "dider.data.simulators.particles.Simulation"
PUSH = "dider.data.simulators.push.Push"
NPZ = "dider.data.readers.trajectories.NpzFile"


def make_dm(tmp_path, **kw) -> ClipsDataModule:
    params = dict(num_train=40, num_val=10, num_test=12, cache_dir=str(tmp_path), loader={"batch_size": 8})
    params.update(kw)
    dm = data_module("synth", **params)
    dm.prepare_data()
    dm.setup()
    return dm


def test_batches_normalised_and_aligned(tmp_path):
    dm = make_dm(tmp_path)
    batch = next(iter(dm.train_dataloader()))
    assert batch["states"].shape == (8, 50, 3, 4) and batch["mask"].all() and batch["edges"].shape == (8, 49, 6)
    train = dm.datasets["train"].states
    assert train.min() >= -1 - 1e-6 and train.max() <= 1 + 1e-6 and train.min() < -0.99
    # edges of transition t -> t+1 are the raw edges of step t+1 (the force that produced x_{t+1})
    states, raw_edges = simulate_push(40, 50, seed=1 * 1000 + 0)
    torch.testing.assert_close(dm.normalizer.normalize(states), train)
    assert torch.equal(dm.datasets["train"].edges, raw_edges[:, 1:])


def test_cache_is_keyed_and_reused(tmp_path):
    dm = make_dm(tmp_path)
    files = sorted(p.name for p in tmp_path.glob("synth_*.pt"))
    assert len(files) == 3 and not list(tmp_path.glob(".*tmp"))
    mtimes = {p: p.stat().st_mtime_ns for p in tmp_path.glob("synth_*.pt")}
    make_dm(tmp_path)  # same parameters: nothing regenerated
    assert {p: p.stat().st_mtime_ns for p in tmp_path.glob("synth_*.pt")} == mtimes
    bigger = make_dm(tmp_path, num_test=20)  # only the test split changes
    assert len(list(tmp_path.glob("synth_*.pt"))) == 4
    assert torch.equal(bigger.datasets["train"].states, dm.datasets["train"].states)


@pytest.mark.parametrize(
    "kw, key",
    [({"num_train": 0}, "data.num_train"), ({"source": {"num_steps": 1}}, "data.source.num_steps")],
)
def test_bad_config_names_the_key(tmp_path, kw, key):
    with pytest.raises(ValueError, match=key):
        data_module("synth", cache_dir=str(tmp_path), **kw)


def test_the_loader_node_overrides_the_data_sets_defaults_key_by_key(tmp_path):
    from dider.data.loader import Loader

    dm = make_dm(tmp_path, loader={"batch_size": 5})
    assert dm.loader == Loader(batch_size=5, eval_batch_size=256)  # the synthetic set's evaluation batch kept
    assert dm.train_dataloader().batch_size == 5 and dm.test_dataloader().batch_size == 256
    assert data_module("basketball").loader == Loader(batch_size=128, eval_batch_size=128)
    with pytest.raises(ValueError, match=r"data.loader.pin_memory='yes': expected true or false"):
        data_module("synth", cache_dir=str(tmp_path), loader={"pin_memory": "yes"})
    with pytest.raises(ValueError, match=r"data.loader.workers: no such setting"):
        data_module("synth", cache_dir=str(tmp_path), loader={"workers": 2})


def test_every_data_setting_is_a_constructor_argument():
    """The data modules check ``locals()`` against their ``SETTINGS`` (a rule no argument has would never run)."""
    import importlib
    import inspect

    from dider.data.common import BaseDataModule

    for name in ("clips", "tracks"):
        importlib.import_module(f"dider.data.{name}")
    classes = set()
    todo = [BaseDataModule]
    while todo:
        todo += (subclasses := todo.pop().__subclasses__())
        classes.update(subclasses)
    assert len(classes) >= 2, sorted(c.__name__ for c in classes)
    for cls in classes:
        params = set(inspect.signature(cls.__init__).parameters)
        assert set(cls.SETTINGS) <= params, (cls.__name__, set(cls.SETTINGS) - params)


def test_normalizer_roundtrip_and_errors():
    x = torch.randn(10, 5, 3, 4)
    n = Normalizer.fit(x)
    torch.testing.assert_close(n.denormalize(n.normalize(x)), x, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="pos_range"):
        Normalizer((1.0, 1.0), (0.0, 1.0))


def test_a_split_setting_a_clip_source_does_not_read_is_refused(tmp_path):
    """The simulators give their splits as made: a split fraction or a carving seed set for them would be ignored
    silently, so it is refused naming the key and the sources that read it."""
    from dider.data.clips import ClipsDataModule

    sizes = {"num_train": 4, "num_val": 2, "num_test": 2}
    with pytest.raises(ValueError, match=rf"data.val_fraction=0.2: data.source._target_={PUSH} gives its splits as "
                                         r"they are; read by a source whose files may lack a validation split"):
        ClipsDataModule(source={"_target_": PUSH}, val_fraction=0.2, **sizes)
    with pytest.raises(ValueError, match=rf"data.split=\[0.6, 0.2, 0.2\]: data.source._target_={SIMULATION} gives"):
        ClipsDataModule(source={"_target_": SIMULATION}, split=[0.6, 0.2, 0.2], **sizes)
    ClipsDataModule(source={"_target_": PUSH}, split=(0.8, 0.1, 0.1), seed=1, **sizes)  # the defaults pass
    ClipsDataModule(source={"_target_": NPZ}, split=[0.6, 0.2, 0.2], seed=4)  # read there


def test_the_normalisers_ranges_by_hand():
    """separate: positions and velocities each by their own min and max; same: one range for all four; none: the
    identity; an absent agent's values (here 99) are never fitted on."""
    from dider.data.clip_source import Clips
    from dider.data.clip_splits import fit_ranges

    states = torch.tensor([[[[0.0, 2.0, -1.0, 0.5], [99.0, 99.0, 99.0, 99.0]]]])  # [S=1, T=1, N=2, 4]
    mask = torch.tensor([[[True, False]]])
    clips = Clips(states, mask)
    separate = fit_ranges(clips, "separate")
    assert separate.pos_range == (0.0, 2.0) and separate.vel_range == (-1.0, 0.5)
    same = fit_ranges(clips, "same")
    assert same.pos_range == same.vel_range == (-1.0, 2.0)
    assert fit_ranges(clips, "none").normalize(states[0, 0, :1]).tolist() == states[0, 0, :1].tolist()
    with pytest.raises(ValueError, match="no present agent"):
        fit_ranges(Clips(states, torch.zeros_like(mask)), "same")
