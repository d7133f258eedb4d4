"""Shared fixtures: configs composed from the packaged dider.conf, with small, fast settings."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, open_dict

os.environ.setdefault("HYDRA_FULL_ERROR", "1")
# trainer.precision's default depends on the CPU (bf16 where it is native); the tests' thresholds were measured
# in fp32, so every run here (and every CLI run they spawn) trains in fp32 unless a test asks otherwise.
os.environ.setdefault("DIDER_DEFAULT_PRECISION", "32-true")
torch.set_num_threads(min(2, torch.get_num_threads()))

# Small and fast: a few hundred clips, narrow networks, a couple of epochs.
TINY = [
    "data.num_train=64", "data.num_val=16", "data.num_test=16", "data.loader.batch_size=16",
    "data.loader.eval_batch_size=16", "protocol.samples=0",
    "model.net.encoder.hidden=32", "model.net.encoder.rnn_hidden=16", "model.net.encoder.head_hidden=16",
    "model.net.decoder.hidden=32", "trainer.max_epochs=1", "trainer.accelerator=cpu",
    "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false",
]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked ``gpu`` run where CUDA is (a lent GPU machine) and are skipped elsewhere."""
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs CUDA")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def one_thread() -> Iterator[None]:
    """Tiny networks on a busy 2-core machine: one thread avoids hand-off costs; and `threads=1` in a
    config must not leak into other tests."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("cache")


@pytest.fixture
def make_cfg(tmp_path: Path, cache_dir: Path) -> Iterator[Callable[..., DictConfig]]:
    """compose(overrides) -> a config whose outputs go to tmp_path and data cache to a shared folder."""

    def _make(overrides: list[str] = (), tiny: bool = True, out: Path | None = None) -> DictConfig:
        GlobalHydra.instance().clear()
        with initialize_config_module(version_base="1.3", config_module="dider.conf"):
            all_overrides = [*(TINY if tiny else []), f"data.cache_dir={cache_dir}", *overrides]
            cfg = compose(config_name="config", overrides=all_overrides, return_hydra_config=True)
        with open_dict(cfg):
            if tiny and "timelines" in (cfg.get("callbacks") or {}):
                cfg.callbacks.timelines.num_clips = 2
            cfg.hydra.runtime.output_dir = str(out or tmp_path / "run")
            cfg.hydra.job.num = 0
            cfg.hydra.job.id = "test"
        HydraConfig().set_config(cfg)
        return cfg

    yield _make
    GlobalHydra.instance().clear()
