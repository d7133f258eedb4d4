"""Hyper-parameter search with Optuna around the app:
`python -m dider.analysis.search hparams_search=dider [overrides]`.

Each trial composes the app's config with the given overrides and the values Optuna suggests from
the space in ``hparams_search`` (conf/hparams_search), trains in ``<out>/trial_<k>`` and reports the
run's ``optimized_metric`` (a validation metric by default, so the search never tunes on the test
set). The trials go to ``<out>/search.csv`` after each one (atomic), the best to
``<out>/best.json``, the study to ``<out>/study.db`` (SQLite): a killed search started again with
``hydra.run.dir=<out>`` goes on where it stopped (``hparams_search.n_trials`` counts the completed
trials), drawing new points; started there with other settings (overrides, space, objective) it is
refused. ``<out>`` is ``hydra.run.dir`` if given, else ``multirun/search/<date>_<time>``. Needs
``pip install optuna``.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf, open_dict

from dider.io import atomic_write_text
from dider.run import fit_and_score, validate_config

log = logging.getLogger(__name__)
KINDS = ("float", "int", "categorical")


def compose_run(overrides: Sequence[str], out: Path) -> DictConfig:
    """The app's config for ``overrides``, with its run folder ``out`` (as ``python -m dider.run``
    would)."""
    GlobalHydra.instance().clear()
    with initialize_config_module(version_base="1.3", config_module="dider.conf"):
        cfg = compose(config_name="config", overrides=list(overrides), return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(out)
        cfg.hydra.job.num, cfg.hydra.job.id = 0, out.name
    HydraConfig().set_config(cfg)
    return cfg


def first_point(space: Mapping[str, Any]) -> dict[str, Any]:
    """A point of the (checked) space: each key at its low end or first choice, for the
    preflight."""
    return {k: spec["choices"][0] if spec["type"] == "categorical" else spec["low"]
            for k, spec in space.items()}


def check_space(space: Mapping[str, Any]) -> None:
    """Each entry ``key -> {type, low, high, log | choices}``; raises naming the key."""
    if not space:
        raise ValueError("hparams_search.space is empty: nothing to search")
    for key, spec in space.items():
        kind = spec.get("type")
        if kind not in KINDS:
            raise ValueError(f"hparams_search.space.{key}.type={kind!r}: expected one of "
                             f"{list(KINDS)}")
        if kind == "categorical":
            if not spec.get("choices"):
                raise ValueError(f"hparams_search.space.{key}: a categorical entry needs choices")
        elif not (isinstance(spec.get("low"), (int, float))
                  and isinstance(spec.get("high"), (int, float))
                  and spec["low"] < spec["high"]):
            raise ValueError(f"hparams_search.space.{key}: needs numbers low < high, got "
                             f"{spec.get('low')!r}, {spec.get('high')!r}")


# Settings a search may change when it goes on: how many trials it makes, where it writes.
GOES_ON_WITH = ("hparams_search.n_trials=", "hydra.run.dir=")


def study_settings(overrides: Sequence[str], spec: Mapping[str, Any],
                   objective: Any) -> dict[str, Any]:
    """What makes a search one search: its overrides (but :data:`GOES_ON_WITH`), space, direction,
    sampler seed and objective; kept in the study, so that a search started again in its folder is
    checked against it."""
    return {"overrides": sorted(o for o in overrides if not o.startswith(GOES_ON_WITH)),
            "space": dict(spec.get("space") or {}), "direction": spec.get("direction", "minimize"),
            "seed": int(spec.get("seed", 1)), "objective": objective}


def check_same_search(out: Path, recorded: Mapping[str, Any] | None,
                      settings: Mapping[str, Any]) -> None:
    """Refuse to go on with a study made with other settings (its trials would mix two
    configurations)."""
    if recorded is None:
        raise ValueError(f"{out / 'study.db'}: a study with no record of its settings (another "
                         "tool's, or an older version's): start this search in another folder "
                         "(hydra.run.dir=...)")
    differ = [f"{k}: the study's {recorded.get(k)!r}, now {settings.get(k)!r}" for k in settings
              if json.dumps(recorded.get(k), sort_keys=True)
              != json.dumps(settings.get(k), sort_keys=True)]
    if differ:
        raise ValueError(f"{out}: holds a search with other settings; going on would mix two "
                         "configurations in one study. Start this one in another folder "
                         "(hydra.run.dir=...), or repeat the study's settings:\n  - "
                         + "\n  - ".join(differ))


def suggest(trial: Any, space: Mapping[str, Any]) -> dict[str, Any]:
    """The trial's value for each key of the space."""
    values = {}
    for key, spec in space.items():
        if spec["type"] == "categorical":
            values[key] = trial.suggest_categorical(key, list(spec["choices"]))
        elif spec["type"] == "int":
            values[key] = trial.suggest_int(key, int(spec["low"]), int(spec["high"]),
                                            log=bool(spec.get("log")))
        else:
            values[key] = trial.suggest_float(key, float(spec["low"]), float(spec["high"]),
                                              log=bool(spec.get("log")))
    return values


def search(overrides: Sequence[str], out: Path | None = None) -> dict[str, Any]:
    """Run the search; returns the best trial ({"number", "value", "params", "dir"})."""
    try:
        import optuna
    except ImportError as e:
        raise ImportError("python -m dider.analysis.search needs optuna: pip install optuna") from e
    base = compose_run(overrides, Path("."))
    if base.get("hparams_search") is None:
        raise ValueError("hparams_search is not set: add hparams_search=dider (or a space of your "
                         "own in conf/hparams_search)")
    spec = OmegaConf.to_container(base.hparams_search, resolve=True)
    space = spec.get("space") or {}
    check_space(space)
    given_dir = next((o.split("=", 1)[1] for o in overrides if o.startswith("hydra.run.dir=")),
                     None)
    out = (out or (Path(given_dir) if given_dir
                   else Path("multirun/search") / time.strftime("%Y-%m-%d_%H-%M-%S")))
    given = [o for o in overrides if not o.startswith("hydra.run.dir=")]
    # the settings pass the preflight (at the space's first point) before the study is made: a
    # corrected command in the same folder is not then refused as "a search with other settings"
    validate_config(compose_run([*given, *(f"{k}={v}" for k, v in first_point(space).items())],
                                out / "preflight"))
    out.mkdir(parents=True, exist_ok=True)
    # the study lives in the search folder: a killed search started again with the same folder goes
    # on
    storage = f"sqlite:///{out.resolve() / 'study.db'}"
    settings = study_settings(given, spec, base.get("optimized_metric"))
    study = optuna.create_study(study_name="dider", storage=storage, load_if_exists=True,
                                direction=spec.get("direction", "minimize"))
    # going on: the same search, never two mixed in one study
    if study.trials or "settings" in study.user_attrs:
        check_same_search(out, study.user_attrs.get("settings"), settings)
    else:
        study.set_user_attr("settings", settings)
    # seeded by the trials already made too: a search that goes on draws new points, not trial 0's
    # again
    study.sampler = optuna.samplers.TPESampler(seed=int(spec.get("seed", 1)) + len(study.trials))
    for trial in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)):
        # a trial the killed search was running: failed; its folder keeps what it wrote, the next
        # trial gets a new one
        log.warning("trial %d (%s) was cut off by the killed search: marked failed", trial.number,
                    out / f"trial_{trial.number:03d}")
        study.tell(trial.number, state=optuna.trial.TrialState.FAIL)
    done = len(study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,)))
    if done:
        log.info("%s: going on with the search: %d trial(s) complete", out, done)

    def objective(trial: Any) -> float:
        values = suggest(trial, space)
        run_dir = out / f"trial_{trial.number:03d}"
        cfg = compose_run([*given, *(f"{k}={v}" for k, v in values.items())], run_dir)
        trial.set_user_attr("dir", str(run_dir))
        try:
            value = fit_and_score(cfg)[1]
        # SIGTERM in the trial: the search stops, to go on from its study later
        except SystemExit as e:
            again = " ".join([*given, f"hydra.run.dir={out}"])
            print(f"search terminated in trial {trial.number}; go on with: python -m "
                  f"dider.analysis.search {again}",
                  file=sys.stderr)
            raise SystemExit(e.code) from None
        # a trial that diverges (or fails otherwise): recorded as failed, the search goes on
        except Exception as e:
            trial.set_user_attr("error", repr(e))
            log.warning("trial %d (%s) failed: %r; the search goes on", trial.number, run_dir, e)
            raise
        return math.inf if value is None or not math.isfinite(value) else float(value)

    # every finished trial of the study, resumed ones included
    def write_trials(study: Any, _: Any) -> None:
        rows = [{"trial": t.number, "value": t.value, **t.params, "dir": t.user_attrs.get("dir")}
                for t in study.get_trials(deepcopy=False,
                                          states=(optuna.trial.TrialState.COMPLETE,))]
        atomic_write_text(out / "search.csv", pd.DataFrame(rows).to_csv(index=False))

    study.optimize(objective, n_trials=max(int(spec.get("n_trials", 20)) - done, 0),
                   callbacks=[write_trials], catch=(Exception,))
    if not study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,)):
        raise RuntimeError(f"{out}: every trial failed (each trial folder's failed.json says why)")
    best = {"number": study.best_trial.number, "value": study.best_value,
            "params": study.best_params, "dir": str(out / f"trial_{study.best_trial.number:03d}"),
            "objective": base.get("optimized_metric"),
            "direction": spec.get("direction", "minimize")}
    atomic_write_text(out / "best.json", json.dumps(best, indent=2))
    print(f"best trial {best['number']}: {best['objective']} = {best['value']:.6g} with "
          f"{best['params']}")
    print(f"trials: {out / 'search.csv'}  best: {out / 'best.json'}")
    return best


def main(argv: Sequence[str] | None = None) -> None:
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s] %(message)s")
    search(list(sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    main()
