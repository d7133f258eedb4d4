"""A training step that never makes the host wait for the device: no ``aten._local_scalar_dense`` (``.item()``,
``bool(tensor)``, ``int(tensor)``) and no op whose output shape depends on the values (``nonzero``, boolean indexing),
in the forward pass, the loss or the backward, for every model option. A GPU runs such a step as one CUDA graph; the
check runs here on the CPU, with the plugins' GPU paths (``sync_free``) chosen."""

from __future__ import annotations

import pytest
import torch

from dider.bench.steps import build_model
from dider.bench.syncs import HostSyncs
from dider.data.common import ClipDataset, PackedClipDataset
from dider.graph import edge_index
from dider.models.plugins import Progress


def step_waits(overrides: list[str], masked: bool, progress: Progress = Progress(3, 100),
               evidence: bool = False) -> dict[str, int]:
    torch.manual_seed(0)
    model, _ = build_model(overrides)
    assert model.objective.reads_evidence(progress) == evidence  # the step checked is the one meant
    model.train()
    if hasattr(model.duration, "sync_free"):
        model.duration.sync_free = True  # the GPU's path
    g = torch.Generator().manual_seed(1)
    states = torch.rand(4, 20, 4, 4, generator=g) * 2 - 1
    mask = torch.ones(4, 20, 4, dtype=torch.bool)
    if masked:  # agents that enter late and leave for a while, as tables and inD have them
        mask[:, :4, 2], mask[:, 9:13, 3] = False, False
    batch = {"states": states * mask[..., None], "mask": mask, "everyone": not masked}
    with HostSyncs() as waits:
        out = model.infer(batch, hard=False, progress=progress)
        model.loss(out, progress)["loss"].backward()
    return dict(waits.where)


@pytest.mark.parametrize("model", ["dnri", "dider", "dider_skid", "dider_paper", "dider_gate", "nri"])
@pytest.mark.parametrize("masked", [False, True])
def test_a_training_step_never_waits_for_the_host(model, masked):
    assert step_waits([f"model={model}"], masked) == {}


def test_the_recurrent_decoder_step_never_waits_for_the_host():
    assert step_waits(["model=dider", "model/net/decoder=recurrent"], masked=False) == {}


@pytest.mark.parametrize("decoder", ["markov", "recurrent"])
@pytest.mark.parametrize("masked", [False, True])
def test_the_indifference_priors_step_never_waits_for_the_host(decoder, masked):  # past its start: evidence scored
    overrides = ["model=dider", f"model/net/decoder={decoder}", "model/net/objective=dider_indifference"]
    assert step_waits(overrides, masked, Progress(1000, 1000), evidence=True) == {}


def test_the_check_sees_a_wait():
    """The dispatch mode does catch what it must: a batch that does not say whether everyone is present makes the
    model read its mask on the host."""
    model, _ = build_model(["model=dnri"])
    batch = {"states": torch.zeros(2, 10, 3, 4), "mask": torch.ones(2, 10, 3, dtype=torch.bool)}
    with HostSyncs() as waits:
        model.infer(batch, hard=False)
    assert any(k.startswith("_local_scalar_dense at models/vae.py") for k in waits.where)


def test_batches_say_whether_everyone_is_present():
    full = ClipDataset(torch.zeros(5, 6, 3, 4), torch.ones(5, 6, 3, dtype=torch.bool))
    assert full.__getitems__([0, 3])["everyone"] is True
    mask = torch.ones(5, 6, 3, dtype=torch.bool)
    mask[4, 2, 1] = False
    assert ClipDataset(torch.zeros(5, 6, 3, 4), mask).__getitems__([0, 1])["everyone"] is False
    packed = PackedClipDataset(torch.zeros(5, 6, 4), torch.ones(5, 6, dtype=torch.bool), torch.tensor([0, 2, 5]))
    assert packed.__getitems__([1])["everyone"] is True
    assert packed.__getitems__([0, 1])["everyone"] is False  # clip 0 padded to 3 agents


def test_edge_index_is_the_off_diagonal_and_stays_on_its_device():
    for n in (1, 2, 3, 6):
        send, recv = edge_index(n)
        assert (send.tolist(), recv.tolist()) == tuple(t.tolist() for t in torch.where(~torch.eye(n, dtype=torch.bool)))
    assert edge_index(4)[0] is edge_index(4)[0]  # made once per device and agent count


def test_in_memory_clips_move_to_the_models_device(make_cfg):
    """``to_device`` (which a GPU run calls at fit start) moves the in-memory splits and makes the next loaders
    worker-free; its batches are then gathered on that device (a dry run on the CPU here)."""
    from hydra.utils import instantiate

    dm = instantiate(make_cfg(["data.loader.num_workers=2"]).data, _convert_="all")
    dm.prepare_data()
    dm.setup("fit")
    dm.to_device(torch.device("cpu"))
    assert dm.loader.num_workers == 0 and not dm.loader.pin_memory
    batch = next(iter(dm.train_dataloader()))
    assert batch["states"].device.type == "cpu" and batch["everyone"] is True and "edges" in batch


@pytest.mark.parametrize("dim", [0, 2, -1])
def test_the_hold_assignments_cumulative_product_has_torchs_gradient_and_reads_nothing_back(dim):
    """torch's cumprod gradient asks the host whether the input holds a zero (a wait on a GPU, which a CUDA graph cannot
    hold); SyncFreeCumprod's is one dense formula: the same numbers, with zeros (several in a slice, at its ends) and
    without."""
    from dider.models.hazard import SyncFreeCumprod

    g = torch.Generator().manual_seed(dim + 5)
    for zeros in (0.0, 0.3):
        x = torch.randn(3, 4, 7, 5, dtype=torch.float64, generator=g)
        x = x.masked_fill(torch.rand(x.shape, generator=g) < zeros, 0.0).requires_grad_()
        grad_out = torch.randn(x.shape, dtype=torch.float64, generator=g)
        expected, = torch.autograd.grad(x.cumprod(dim), x, grad_out)
        y = SyncFreeCumprod.apply(x, dim)
        with HostSyncs() as waits:
            got, = torch.autograd.grad(y, x, grad_out)
        assert waits.where == {} and torch.equal(y, x.cumprod(dim))
        assert torch.allclose(got, expected, rtol=1e-10, atol=1e-12)
    with_zeros = torch.randn(3, 6, dtype=torch.float64, generator=g).index_fill(1, torch.tensor([1, 4]), 0.0)
    assert torch.autograd.gradcheck(lambda t: SyncFreeCumprod.apply(t, 1), (with_zeros.requires_grad_(),))
