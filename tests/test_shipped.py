"""The trained models shipped inside the package load by name and score what their records say."""

from __future__ import annotations

import math

import pytest
import torch

import dider
from dider.analysis.ship import evaluate
from dider.shipped import HERE, catalog


def test_the_catalog_names_files_that_ship_and_say_how_they_were_made():
    assert dider.pretrained() == {name: record["what"] for name, record in catalog().items()}
    assert {"synth/dider", "synth/dnri"} <= set(catalog())
    for name, record in catalog().items():
        assert (HERE / record["file"]).is_file(), name
        assert record["trained_with"].startswith("python -m dider.run ") and record["git_commit"], name
        assert record["metrics"] and record["evaluate"], name


@pytest.mark.parametrize("name", sorted(catalog()))
def test_a_shipped_model_reproduces_its_recorded_test_metrics(name):
    """The record's own command (``mode=eval ckpt_path=NAME``, test clips regenerated from the data seed), in a
    fresh process, within float tolerance: another CPU's matrix products round differently (across the CPUs the
    records were made and checked on, 6e-6 relative at most: the bound leaves over 100 times that)."""
    record = catalog()[name]
    again = evaluate(name, record["evaluate"])
    assert set(record["metrics"]) <= set(again)  # every recorded metric is scored again (a test pass may add some)
    off = {k: (v, again[k]) for k, v in record["metrics"].items()
           if not (math.isnan(v) and math.isnan(again[k])) and again[k] != pytest.approx(v, rel=1e-3, abs=1e-9)}
    assert not off, off


def test_a_shipped_model_loads_by_name_for_the_api():
    model = dider.load("synth/dider")
    assert model.path == HERE / catalog()["synth/dider"]["file"] and model.config["name"] == "dider"
    with pytest.raises(FileNotFoundError, match="nor a shipped model .*synth/dider"):
        dider.load("synth/no_such_model")


def test_a_setting_newer_than_a_checkpoint_reads_as_its_constructors_default():
    """A plugin setting added after a checkpoint was written (the shipped ones have no ``prediction_steps``) is
    compared at its constructor's default, so ``ckpt_path=`` still accepts the checkpoint."""
    from dider.training.runfolder import signature_default

    flat = {"decoder._target_": "dider.models.decoders.MarkovDecoder"}
    assert signature_default(flat, "decoder.prediction_steps") == 1
    assert signature_default(flat, "decoder.no_such_setting") is None
    assert signature_default({"decoder._target_": "no.such.Class"}, "decoder.hidden") is None


def test_shipping_records_the_command_the_commit_and_how_long_training_ran(tmp_path, monkeypatch):
    import functools
    import json
    import shutil

    from dider.analysis import ship

    run, package = tmp_path / "run", tmp_path / "shipped"
    (run / "checkpoints").mkdir(parents=True)
    package.mkdir()
    shutil.copy(HERE / catalog()["synth/dnri"]["file"], run / "checkpoints" / "last.ckpt")
    (run / "metrics.json").write_text(json.dumps({
        "metrics": {}, "overrides": ["model=dnri", "seed=1", "hydra.run.dir=x", "logger=csv"],
        "provenance": {"git_commit": "abc", "wall_s": 600.0, "device": "cpu"}}))
    (package / "catalog.json").write_text("{}")
    monkeypatch.setattr(ship, "HERE", package)
    monkeypatch.setattr(ship, "catalog", functools.cache(lambda: json.loads((package / "catalog.json").read_text())))
    monkeypatch.setattr(ship, "evaluate", lambda name, overrides: {"test/ade/h15": 0.5})
    record = ship.ship(run, "mine/dnri", "DNRI of mine", ["model=dnri"])
    assert record == {"file": "mine_dnri.ckpt", "what": "DNRI of mine", "trained_with": "python -m dider.run "
                      "model=dnri seed=1", "git_commit": "abc", "evaluate": ["model=dnri"],
                      "metrics": {"test/ade/h15": 0.5}, "trained_wall_s": 600.0, "trained_device": "cpu"}
    assert json.loads((package / "catalog.json").read_text())["mine/dnri"] == record
    assert "optimizer_states" not in torch.load(package / "mine_dnri.ckpt", weights_only=False)
