"""``mode=eval``: a checkpoint is tested on clips read the way it was trained (its normaliser, its frame rate), into a
folder of its own, never over a training run's results."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from dider.run import ConfigError, train
from dider.training.runfolder import RunRefused
from helpers.fixtures import write_trajectories

pytestmark = pytest.mark.usefixtures("one_thread")

# trajectories read at 10 frames per second (the data config's default is 1)
DATA = ["experiment=smoke", "data=trajectories", "data.source.frame_rate=10", "protocol.horizons=[1,5]", "logger=none",
        "callbacks.timelines.num_clips=0", "trainer.enable_progress_bar=false"]


def metrics_of(folder: Path) -> dict[str, float]:
    return json.loads((folder / "metrics.json").read_text())["metrics"]


def same(a: dict[str, float], b: dict[str, float]) -> bool:
    return a.keys() == b.keys() and all(a[k] == b[k] or (math.isnan(a[k]) and math.isnan(b[k])) for k in a)


@pytest.fixture
def trained(make_cfg, tmp_path) -> tuple[Path, Path]:
    """A run trained on an npz at data.source.frame_rate=10 with every clip's split: (the run, the npz)."""
    npz = tmp_path / "tracks.npz"
    write_trajectories(npz, num=60, steps=16, agents=3)
    run = tmp_path / "run"
    train(make_cfg([*DATA, f"data.source.path={npz}"], tiny=False, out=run))
    return run, npz


def test_eval_reads_the_clips_as_the_checkpoint_was_trained(make_cfg, tmp_path, trained):
    """Another training split (data.num_train=8) would fit another normaliser, and the data config's frame rate
    (1, not repeated on the command line) other velocities: evaluation uses the checkpoint's and gives exactly the
    training run's test metrics. A frame rate set to another value is refused naming both, unless eval.force."""
    run, npz = trained
    data = ["experiment=smoke", "data=trajectories", f"data.source.path={npz}", "protocol.horizons=[1,5]",
            "logger=none",
            "callbacks.timelines.num_clips=0", "mode=eval", f"ckpt_path={run}"]
    evaluated = train(make_cfg([*data, "data.num_train=8"], tiny=False, out=tmp_path / "eval"))
    assert same(evaluated, metrics_of(run))
    with pytest.raises(ConfigError,
                       match=r"data.source.frame_rate=4: the checkpoint .* was trained with data.source.frame_rate=10"
                                          r".*eval.force=true"):
        train(make_cfg([*data, "data.source.frame_rate=4"], tiny=False, out=tmp_path / "other_rate"))
    forced = train(make_cfg([*data, "data.source.frame_rate=4",
                   "eval.force=true"], tiny=False, out=tmp_path / "forced"))
    assert forced["test/ade/h05"] != evaluated["test/ade/h05"]


def test_eval_in_a_training_run_writes_beside_its_results(make_cfg, tmp_path, trained):
    """ckpt_path=last in the training run's folder: the results go to eval/<data config>/ there and the training's
    own metrics.json is left as it was; a second evaluation into the same folder is refused, eval.name gives
    another."""
    run, npz = trained
    before = (run / "metrics.json").read_bytes()
    again = [*DATA, f"data.source.path={npz}", "mode=eval", "ckpt_path=last"]
    evaluated = train(make_cfg(again, tiny=False, out=run))
    assert (run / "metrics.json").read_bytes() == before
    assert same(metrics_of(run / "eval" / "trajectories"), evaluated)
    assert (run / "eval" / "trajectories" / "segments.json").exists()
    record = json.loads((run / "eval" / "trajectories" / "metrics.json").read_text())
    assert record["mode"] == "eval" and record["checkpoint"] == str(run / "checkpoints" / "last.ckpt")
    with pytest.raises(RunRefused, match=r"eval/trajectories already holds an evaluation .*eval.name=OTHER"):
        train(make_cfg(again, tiny=False, out=run))
    train(make_cfg([*again, "eval.name=second"], tiny=False, out=run))
    assert (run / "eval" / "second" / "metrics.json").exists()
