"""Training steps replayed from one CUDA graph (the top-level ``cuda_graph`` setting). On a CPU the same path runs as
a dry run (the step's function on static-style buffers, manual optimisation, the schedules as tensors): it must train
exactly as Lightning's own loop does, resume as it does, and refuse trainer settings it cannot keep. The capture
itself is checked on a GPU (tests/test_gpu.py)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from dider.run import train
from dider.training.graphed import wanted
from dider.training.step_graph import StepGraph


def identical(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(a[k] == b[k] or (math.isnan(a[k]) and math.isnan(b[k])) for k in a)


# 72 clips: four batches of 16 and a last one of 8 (another shape); the KL weight and the learning rate move
SCHEDULES = ["seed=3", "logger=none", "trainer.max_epochs=2", "data.num_train=72", "model.scheduler.step_size=1",
             "model.net.objective.kl_warmup=0.6"]


# the segment end's path with a term switched on mid-run (the indifference prior's `on/` weight, a device scalar in
# the graph; the evidence's pass and its backed share); the plain segment end's and the Gaussian's, about 30 s more
# each: make test-all
@pytest.mark.parametrize("model", [
    ["model=dider", "model.net.objective.indifference.after=0.5", "model.net.objective.indifference.from_step=0",
     "model.net.objective.indifference.weighting=backed_share"],
    pytest.param(["model=dider"], marks=pytest.mark.slow),
    pytest.param(["model=dider_paper"], marks=pytest.mark.slow)], ids=["indifference", "dider", "dider_paper"])
def test_the_graphed_step_trains_as_lightnings_loop(make_cfg, tmp_path, model):
    eager = train(make_cfg([*model, *SCHEDULES, "cuda_graph=false"], out=tmp_path / "eager"))
    graphed = train(make_cfg([*model, *SCHEDULES, "cuda_graph=true"], out=tmp_path / "graphed"))
    assert "test/nll" in eager and identical(eager, graphed)
    if "indifference" in str(model):
        assert eager["test/indifference"] > 0


@pytest.mark.slow  # three runs, about 65 s: make test-all (the eager resume: tests/test_reliability.py)
def test_a_graphed_run_resumes_to_the_uninterrupted_numbers(make_cfg, tmp_path):
    """SIGTERM after batch 3 of epoch 2 and ckpt_path=last, with the steps graphed: Lightning's own step count and
    checkpoints, so the resumed run equals the uninterrupted one."""
    base = ["seed=3", "logger=none", "trainer.max_epochs=2", "data.num_train=96", "cuda_graph=true"]
    whole = train(make_cfg(base, out=tmp_path / "whole"))
    stop = ["+callbacks.stop._target_=helpers.signals.TerminateAt", "+callbacks.stop.epoch=1",
            "+callbacks.stop.batch=2"]
    with pytest.raises(SystemExit):
        train(make_cfg(base + stop, out=tmp_path / "run"))
    last = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert last["global_step"] == 9
    resumed = train(make_cfg(base + ["ckpt_path=last"], out=tmp_path / "run"))
    assert identical(resumed, whole)


def trainer_with(**settings) -> SimpleNamespace:
    from lightning.pytorch.accelerators import CPUAccelerator

    values = {"gradient_clip_val": None, "accumulate_grad_batches": 1, "precision_plugin": None,
              "precision": "32-true", "world_size": 1, "num_devices": 1, "accelerator": CPUAccelerator()}
    return SimpleNamespace(**(values | settings))


def test_the_setting_graphs_where_it_can_and_names_what_it_cannot_keep():
    assert not wanted("auto", trainer_with())  # a CPU: Lightning's loop
    assert wanted(True, trainer_with()) and not wanted(False, trainer_with()) and not wanted("auto", None)
    with pytest.raises(ValueError, match=r"trainer.gradient_clip_val=1.0.*cuda_graph=false"):
        wanted(True, trainer_with(gradient_clip_val=1.0))
    with pytest.raises(ValueError, match="trainer.accumulate_grad_batches=2"):
        wanted(True, trainer_with(accumulate_grad_batches=2))
    with pytest.raises(ValueError, match="cuda_graph='yes': expected auto, true or false"):
        wanted("yes", trainer_with())


def test_a_clipped_run_refuses_the_graph_before_training(make_cfg, tmp_path):
    with pytest.raises(ValueError, match="trainer.gradient_clip_val"):
        train(make_cfg(["logger=none", "cuda_graph=true", "trainer.gradient_clip_val=1.0"], out=tmp_path / "run"))


def test_the_dry_run_reads_its_inputs_and_scalars_each_step():
    seen = []
    graph = StepGraph(lambda inputs, flags: seen.append((inputs["x"].sum().item(), inputs["w"].item(), flags)) or {})
    graph({"x": torch.ones(3)}, {"w": 0.5}, True)
    graph({"x": torch.full((3,), 2.0)}, {"w": 0.25}, True)
    graph({"x": torch.ones(2)}, {"w": 1.0}, False)
    assert seen == [(3.0, 0.5, True), (6.0, 0.25, True), (2.0, 1.0, False)] and graph.eager_calls == 3
    with pytest.raises(ValueError, match="warmup=0"):
        StepGraph(lambda inputs, flags: {}, warmup=0)


def test_epoch_means_weigh_each_step_by_its_batch_and_read_nothing_back():
    from dider.bench.syncs import HostSyncs
    from dider.training.step_metrics import EpochMeans

    means = EpochMeans()
    steps = [({"loss": torch.tensor(2.0), "kl": torch.tensor(1.0), "tau": 0.5}, 16),
             ({"loss": torch.tensor(5.0), "kl": torch.tensor(0.0), "tau": 0.25}, 8)]
    with HostSyncs() as waits:
        for values, weight in steps:
            means.add(values, weight)
    assert waits.where == {}
    got = {k: float(v) for k, v in means.means().items()}
    assert got == pytest.approx({"loss": (2 * 16 + 5 * 8) / 24, "kl": 16 / 24, "tau": (0.5 * 16 + 0.25 * 8) / 24})
    assert {k: float(v) for k, v in means.last().items()} == {"loss": 5.0, "kl": 0.0}
    means.reset()
    assert means.means() == {} and means.weight == 0
    with pytest.raises(ValueError, match="differ from the epoch's"):
        means.add({"loss": torch.tensor(1.0)}, 4)
        means.add({"nll": torch.tensor(1.0)}, 4)
