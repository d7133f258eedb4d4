"""Hyper-parameter search with Optuna on a validation objective (optional extra: skipped without optuna)."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from dider.analysis.search import check_space, search

optuna = pytest.importorskip("optuna")

SMOKE = ["experiment=smoke", "logger=none", "trainer.enable_progress_bar=false", "callbacks.timelines.num_clips=0",
         "data.num_train=32", "data.num_val=8", "data.num_test=8", "trainer.max_epochs=2",
         "model.net.objective.kl_warmup=0"]


def test_two_trials_on_the_validation_objective(tmp_path, cache_dir):
    out = tmp_path / "search"
    best = search([*SMOKE, f"data.cache_dir={cache_dir}", "hparams_search=dider", "hparams_search.n_trials=2",
                   f"hydra.run.dir={out}"])
    trials = pd.read_csv(out / "search.csv")
    assert list(trials["trial"]) == [0, 1] and trials["value"].notna().all()
    assert trials["model.optimizer.lr"].between(1e-4, 3e-3).all()
    assert trials["model.net.objective.kl_warmup"].between(0, 0.5).all()
    for _, row in trials.iterrows():
        record = json.loads((out / f"trial_{int(row['trial']):03d}" / "metrics.json").read_text())
        assert record["objective"] == pytest.approx(row["value"])  # the validation metric, not a test metric
        assert record["config"]["optimized_metric"] == "val/select"
        assert record["config"]["model"]["optimizer"]["lr"] == pytest.approx(row["model.optimizer.lr"])
    assert best["value"] == trials["value"].min() and json.loads((out / "best.json").read_text())["number"] == \
        int(trials.loc[trials["value"].idxmin(), "trial"])


@pytest.mark.parametrize("space, key", [({}, "space is empty"), ({"a": {"type": "normal"}}, "space.a.type"),
                                        ({"a": {"type": "float", "low": 1, "high": 0}}, "space.a: needs"),
                                        ({"a": {"type": "categorical"}}, "needs choices")])
def test_bad_space_is_named(space, key):
    with pytest.raises(ValueError, match=key):
        check_space(space)


@pytest.mark.slow  # about 20 s: make test-all
def test_a_killed_search_goes_on_from_its_study(tmp_path, cache_dir):
    """A search stopped after one trial, with a second one cut off (still RUNNING in its study), started again
    with the same folder: the cut-off trial is marked failed, one new trial completes the two asked for, at a new
    point (not trial 0's again). Started there with other settings, the search is refused before any trial."""
    out = tmp_path / "search"
    args = [*SMOKE, f"data.cache_dir={cache_dir}", "hparams_search=dider", f"hydra.run.dir={out}"]
    search([*args, "hparams_search.n_trials=1"])
    study = optuna.load_study(study_name="dider", storage=f"sqlite:///{out / 'study.db'}")
    study.ask()  # trial 1: what a killed search leaves behind
    search([*args, "hparams_search.n_trials=2"])
    trials = pd.read_csv(out / "search.csv")
    assert list(trials["trial"]) == [0, 2] and trials["value"].notna().all()
    study = optuna.load_study(study_name="dider", storage=f"sqlite:///{out / 'study.db'}")
    states = [t.state.name for t in study.trials]
    assert states == ["COMPLETE", "FAIL", "COMPLETE"]
    assert study.trials[2].params != study.trials[0].params
    with pytest.raises(ValueError, match=r"holds a search with other settings.*\n  - overrides: "):
        search([*args, "hparams_search.n_trials=3", "trainer.max_epochs=1"])
    assert len(optuna.load_study(study_name="dider", storage=f"sqlite:///{out / 'study.db'}").trials) == 3


def test_a_failing_trial_is_recorded_and_the_search_goes_on(tmp_path, cache_dir, monkeypatch):
    """Trial 0 diverges: it is a failed trial with its error recorded, and trial 1 still runs and is the best."""
    import dider.analysis.search as search_module

    real, calls = search_module.fit_and_score, []

    def diverging_first(cfg):
        calls.append(cfg)
        if len(calls) == 1:
            raise ValueError("non-finite loss at step 3 (term nll)")
        return real(cfg)

    monkeypatch.setattr(search_module, "fit_and_score", diverging_first)
    out = tmp_path / "search"
    best = search([*SMOKE, f"data.cache_dir={cache_dir}", "hparams_search=dider", "hparams_search.n_trials=2",
                   f"hydra.run.dir={out}"])
    study = optuna.load_study(study_name="dider", storage=f"sqlite:///{out / 'study.db'}")
    assert [t.state.name for t in study.trials] == ["FAIL", "COMPLETE"]
    assert "non-finite loss" in study.trials[0].user_attrs["error"]
    assert best["number"] == 1 and list(pd.read_csv(out / "search.csv")["trial"]) == [1]


def test_a_search_refused_by_the_preflight_records_no_study(tmp_path, cache_dir):
    out = tmp_path / "search"
    args = [*SMOKE, f"data.cache_dir={cache_dir}", "hparams_search=dider", "hparams_search.n_trials=1",
            f"hydra.run.dir={out}"]
    with pytest.raises(ValueError, match=r"model.num_edges=1: must be >= 2"):
        search([*args, "model.num_edges=1"])
    assert not out.exists()  # the corrected command starts the search afresh
    search([*args, "model.num_edges=2"])
    assert len(optuna.load_study(study_name="dider", storage=f"sqlite:///{out / 'study.db'}").trials) == 1
