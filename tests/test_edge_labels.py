"""Ground-truth edge labels and the model's types are matched before any work: labels beyond ``model.num_edges``
are refused once the data are read, naming the file, the largest label and the key, in training and in eval."""

from __future__ import annotations

import numpy as np
import pytest
from tests.helpers.fixtures import write_trajectories

from dider.run import train

pytestmark = pytest.mark.usefixtures("one_thread")


def _labelled(path, top: int):
    """An npz of random walks whose edge labels take every value 0..top."""
    arrays = write_trajectories(path, num=48, steps=16, agents=3)
    rng = np.random.default_rng(1)
    edges = rng.integers(0, top + 1, (48, 16, 6))
    edges[0, 0, 0] = top
    np.savez(path, **arrays, edges=edges)
    return path


def _data(path) -> list[str]:
    return ["data=trajectories", f"data.source.path={path}", "protocol.burn_in=4", "protocol.horizons=[1,4]",
            "logger=none", "callbacks.timelines.num_clips=0"]


def test_labels_beyond_the_types_are_refused_before_training(make_cfg, tmp_path):
    path = _labelled(tmp_path / "three_types.npz", 2)
    run = tmp_path / "run"
    with pytest.raises(ValueError) as refused:
        train(make_cfg([*_data(path), "model.num_edges=2"], out=run))
    message = str(refused.value)
    assert str(path) in message and "up to 2" in message and "model.num_edges=2" in message
    assert "model.num_edges=3" in message  # the way out
    assert not list(run.glob("checkpoints/*.ckpt"))  # nothing trained


def test_labels_within_the_types_train_and_score(make_cfg, tmp_path):
    path = _labelled(tmp_path / "three_types.npz", 2)
    metrics = train(make_cfg([*_data(path), "model.num_edges=3"], out=tmp_path / "run"))
    assert 0.0 <= metrics["test/edge_acc/posterior/matched"] <= 1.0


def test_eval_of_a_checkpoint_on_labels_beyond_its_types_is_refused(make_cfg, tmp_path):
    run = tmp_path / "run"
    train(make_cfg([*_data(_labelled(tmp_path / "two_types.npz", 1)), "model.num_edges=2"], out=run))
    path = _labelled(tmp_path / "four_types.npz", 3)
    with pytest.raises(ValueError, match=r"four_types.npz: the test split's edge labels go up to 3, and the model "
                                         r"has model.num_edges=2"):
        train(make_cfg([*_data(path), "mode=eval", f"ckpt_path={run}"], out=tmp_path / "eval"))
