"""Tracking beyond TensorBoard (MLflow's file store, CSV) and the standard callbacks as configs."""

from __future__ import annotations

import pytest
from hydra.utils import instantiate
from lightning.pytorch.callbacks import EarlyStopping, LearningRateMonitor
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from dider.run import train

mlflow = pytest.importorskip("mlflow")


@pytest.mark.slow  # about 12 s: make test-all
def test_mlflow_store_gets_params_metrics_and_figures(make_cfg, tmp_path):
    store = f"sqlite:///{tmp_path / 'mlflow.db'}"
    train(make_cfg(["logger=[csv,mlflow]", f"logger.mlflow.tracking_uri={store}",
                    f"logger.mlflow.artifact_location={tmp_path / 'artifacts'}", "seed=3"], out=tmp_path / "run"))
    client = mlflow.tracking.MlflowClient(tracking_uri=store)
    (run,) = client.search_runs([client.get_experiment_by_name("dider").experiment_id])
    assert run.info.run_name == "dider-seed3"
    assert run.data.params["seed"] == "3" and run.data.params["model"] == "dider"
    assert "test/mse/h01" in run.data.metrics and "train/lr" in run.data.metrics
    figures = [a.path for a in client.list_artifacts(run.info.run_id, "figures")]
    assert "figures/test_timeline_00.png" in figures and "figures/test_trajectories_00.png" in figures
    assert "seed: 3" in (tmp_path / "run" / "csv" / "hparams.yaml").read_text()  # the CSV logger too


def test_learning_rate_in_tensorboard_and_no_logger_runs(make_cfg, tmp_path):
    train(make_cfg([], out=tmp_path / "tb"))
    acc = EventAccumulator(str(tmp_path / "tb" / "tb"))
    acc.Reload()
    assert "train/lr" in acc.Tags()["scalars"]
    train(make_cfg(["logger=none"], out=tmp_path / "none"))  # the monitor is left out: nothing to write to
    assert (tmp_path / "none" / "metrics.json").exists()


def test_callback_configs_compose(make_cfg):
    stopping = [instantiate(c) for c in make_cfg(["callbacks=early_stopping"]).callbacks.values()]
    es = next(c for c in stopping if isinstance(c, EarlyStopping))
    assert es.monitor == "val/select" and not es.check_finite  # inf inside the KL warm-up is not a stop
    assert any(isinstance(c, LearningRateMonitor) for c in stopping)
    pytest.importorskip("rich")
    from lightning.pytorch.callbacks import RichProgressBar

    rich = [instantiate(c) for c in make_cfg(["callbacks=rich"]).callbacks.values()]
    assert any(isinstance(c, RichProgressBar) for c in rich)


def test_early_stopping_stops_a_run(make_cfg, tmp_path):
    metrics = train(make_cfg(["callbacks=early_stopping", "callbacks.early_stopping.patience=1",
                              "callbacks.early_stopping.min_delta=1e9", "trainer.max_epochs=6",
                              "model.net.objective.kl_warmup=0", "logger=none"], out=tmp_path / "run"))
    import torch

    last = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert last["epoch"] < 5 and "test/mse/h01" in metrics  # stopped early (no improvement of 1e9), then tested


def test_a_runs_tensorboard_name_carries_every_swept_setting(monkeypatch):
    from omegaconf import OmegaConf

    from dider.outputs import run_record

    given = ["experiment=edge_ablation", "model=dider", "seed=2", "model.num_edges=6", "+data.options={limit:30}",
             "hydra.sweep.dir=x", "logger=csv", "data.source.root=/d", "trainer.precision=32-true"]
    monkeypatch.setattr(run_record, "overrides", lambda: given)
    cfg = OmegaConf.create({"model": {"name": "dider"}, "seed": 2})
    assert run_record.run_label(cfg) == \
        "dider-seed2-model.num_edges=6-data.options={limit.30}-trainer.precision=32-true"
