"""A committed record of sweeps: every job's metrics, per-model summaries and differences paired by
seed.

    python -m dider.analysis.record SWEEP [SWEEP ...] --out docs/records/NAME.json [--baseline dnri]
        [--command "the command that ran the sweeps"] [--metric test/mse/h15 ...] [--curve
        val/mse/h01 ...]

Reads each job's ``metrics.json`` (a sweep's subfolders, or run folders given directly; a job still
running, failed or with a broken record is named in a warning and listed under ``unfinished``; two
jobs of one model and seed are refused), and for ``train/`` and ``val/`` metrics the last value the
job's CSV log (``csv/metrics.csv``, ``logger=csv``) holds; keys it by its model's name and seed
(with ``--curve``, a metric's course over the epochs too), and writes one JSON file: the jobs, and
per model the mean, sample std, min and max of each metric and, against ``--baseline``, the mean and
standard error of the difference model - baseline over the seeds both have. The documentation quotes
these files, so each of its figures comes with its record.

``--jobs-from RECORD:MODEL`` takes a model's jobs from a committed record as it recorded them (their
metrics, curves and provenance; the run folders need not exist any more), for a new configuration
paired against a baseline that was run and recorded before.
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dider.io import atomic_write_text
from dider.training.run_lock import LOCK, owner_of

log = logging.getLogger(__name__)

# What a record keeps of each job when no --metric is given: the forecast (in data units against
# constant velocity, and as the normalised MSE), edge recalls, the own cut. A job that lacks a key
# leaves it out.
DEFAULT_METRICS = (
    "test/ade/h01", "test/ade/h15", "test/ade/h25", "test/cv/ade/h01", "test/cv/ade/h15",
    "test/cv/ade/h25", "test/ade_vs_cv/h01", "test/ade_vs_cv/h15", "test/ade_vs_cv/h25",
    "test/mse/h01", "test/mse/h15", "test/mse/h25", "test/ade_vs_no_edges/h15",
    "test/ade_vs_no_edges/h25", "test/min_ade_6/h15", "test/min_ade_6/h25", "test/min_fde_6/h25",
    "test/segments/per_constant_edge", "test/mse_posterior/h15", "test/mse_posterior/h25",
    "test/mse_oracle/h15", "test/mse_oracle/h25", "test/edge_acc/posterior/none",
    "test/edge_acc/posterior/interaction", "test/edge_acc/prior/none",
    "test/edge_acc/prior/interaction",
    "test/edge_acc/prior_per_step/interaction", "test/segments_per_edge", "test/boundary_f1",
    "test/segments/segments_per_edge", "test/segments/steps_per_segment", "test/segments/on_switch",
    "test/segments/boundary_f1", "test/run_length/posterior", "test/run_length/prior",
    "test/run_length/truth", "train/segments/steps_per_segment", "test/edge_acc/posterior/matched",
    "test/edge_acc/posterior/as_labelled",
    "test/edge_auroc/posterior", "test/edge_acc/prior/matched",
)


def job_folders(paths: Sequence[Path]) -> list[Path]:
    """Run folders: each path that is one (it holds a ``metrics.json``, a ``failed.json``, a run's
    lock or its ``.hydra`` record), else its subfolders that are (a sweep)."""
    found = []
    for path in paths:
        if is_job(path):
            found.append(path)
        elif path.is_dir():
            found.extend(sorted(p for p in path.iterdir() if p.is_dir() and is_job(p)))
        else:
            raise FileNotFoundError(f"{path}: no such run or sweep folder")
    if not found:
        raise FileNotFoundError(f"{', '.join(map(str, paths))}: no job with a metrics.json")
    return found


def is_job(folder: Path) -> bool:
    return any((folder / name).exists() for name in ("metrics.json", "failed.json", LOCK, ".hydra"))


def read_job(folder: Path) -> tuple[dict[str, Any] | None, str]:
    """A job's ``metrics.json`` record, or None and what it is instead: ``running`` (a live run
    holds the folder), ``failed: <why>`` (its ``failed.json``, or a record that is missing,
    half-written or not a run's)."""
    if (lock := owner_of(folder)) is not None:
        return None, f"running (pid {lock.get('pid')} on {lock.get('host')})"
    path = folder / "metrics.json"
    try:
        record = json.loads(path.read_text())
    except OSError:
        failed = folder / "failed.json"
        why = ("no metrics.json" + (f"; {failed.name} says {_error(failed)}" if failed.exists()
                                    else ""))
        return None, f"failed: {why}"
    except ValueError as e:
        return None, f"failed: {path} is not JSON (half-written?): {e}"
    if (not isinstance(record, dict) or not isinstance(record.get("metrics"), dict)
        or "seed" not in record):
        return (None,
                f"failed: {path} is not a run's record (a JSON object with 'metrics' and 'seed')")
    return record, "finished"


def _error(failed: Path) -> str:
    try:
        return str(json.loads(failed.read_text()).get("error", "?"))
    except (OSError, ValueError, AttributeError):
        return "nothing readable"


def logged_curves(folder: Path, names: Sequence[str]) -> dict[str, list[list[float]]]:
    """Each of ``names`` over training from the job's CSV log: [[epoch, step, value], ...] of the
    rows that hold it (epoch, step None where the log has no such column); {} without a log."""
    path = folder / "csv" / "metrics.csv"
    if not names or not path.is_file():
        return {}
    curves: dict[str, list[list[float]]] = {k: [] for k in names}
    with path.open(newline="") as f:
        for row in csv.DictReader(f):
            for k in names:
                if row.get(k) not in (None, ""):
                    curves[k].append([_count(row.get("epoch")), _count(row.get("step")),
                                      float(row[k])])
    return {k: v for k, v in curves.items() if v}


def _count(value: str | None) -> int | None:
    return None if value in (None, "") else int(value)


def last_logged(folder: Path, names: Sequence[str]) -> dict[str, float]:
    """The last non-empty value of each of ``names`` in the job's CSV log (``csv/metrics.csv``); {}
    without one."""
    return {k: points[-1][2] for k, points in logged_curves(folder, names).items()}


def summary(values: list[float]) -> dict[str, float]:
    n = len(values)
    mean = sum(values) / n
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1)) if n > 1 else math.nan
    return {"n": n, "mean": mean, "std": std, "min": min(values), "max": max(values)}


def paired(model: dict[int, float], baseline: dict[int, float]) -> dict[str, float] | None:
    """model - baseline over the seeds both have: mean, standard error, and on how many seeds it is
    below 0."""
    seeds = sorted(set(model) & set(baseline))
    if not seeds:
        return None
    diffs = [model[s] - baseline[s] for s in seeds]
    stats = summary(diffs)
    # 0 where the baseline has none of it (DNRI's own boundaries)
    total = sum(baseline[s] for s in seeds)
    return {"n": stats["n"], "mean": stats["mean"], "se": stats["std"] / math.sqrt(stats["n"]),
            "below": sum(d < 0 for d in diffs),
            "ratio_of_means": sum(model[s] for s in seeds) / total if total else math.nan}


def recorded_jobs(spec: str, metrics: Sequence[str]) -> list[dict[str, Any]]:
    """``RECORD:MODEL`` -> the jobs of MODEL in the record file RECORD, as recorded (the kept
    ``metrics`` only), each naming the record it came from."""
    path, sep, model = spec.rpartition(":")
    if not sep or not path or not model:
        raise ValueError(f"--jobs-from {spec}: expected RECORD:MODEL, e.g. "
                         "docs/records/protocol.json:dnri")
    try:
        record = json.loads(Path(path).read_text())
        jobs = [j for j in record["jobs"] if j["model"] == model]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"--jobs-from {spec}: {path} is not a readable record "
                         f"({type(e).__name__}: {e})") from None
    if not jobs:
        raise ValueError(f"--jobs-from {spec}: {path} records no job of model {model!r}; its "
                         f"models: {sorted({j['model'] for j in record['jobs']})}")
    return [dict(j, metrics={k: v for k, v in j["metrics"].items() if k in metrics},
                 recorded_in=path)
            for j in jobs]


def build(paths: Sequence[Path], metrics: Sequence[str], baseline: str | None, command: str | None,
          label: str = "name", by_overrides: bool = True, curves: Sequence[str] = (),
          rename: dict[str, str] | None = None, borrowed: Sequence[str] = ()) -> dict[str, Any]:
    """rename: a group's label -> the label it is recorded under (one configuration spelt by two
    sets of overrides, recorded as one model). borrowed: ``RECORD:MODEL`` specs
    (:func:`recorded_jobs`), added under their recorded labels."""
    jobs, unfinished = [], []
    for folder in job_folders(paths) if paths else ():
        record, state = read_job(folder)
        if record is None:
            log.warning("%s: %s; left out of the record", folder, state)
            unfinished.append({"folder": str(folder), "state": state})
            continue
        model = record.get("config", {}).get("model", {})
        kept = {k: record["metrics"][k] for k in metrics if k in record["metrics"]}
        kept |= last_logged(folder, [k for k in metrics if k.startswith(("train/", "val/"))])
        job = {"folder": str(folder), "model": model.get(label, record.get("model")),
               "seed": record["seed"],
               "overrides": [o for o in record.get("overrides", []) if not o.startswith("seed=")],
               "metrics": kept,
               # what the job cost and which code ran it, as the run's own record says
               "provenance": {k: record.get("provenance", {}).get(k)
                              for k in ("wall_s", "device", "git_commit")}}
        if curves:
            job["curves"] = logged_curves(folder, curves)
        jobs.append(job)
    if not jobs and not borrowed:
        raise FileNotFoundError(f"{', '.join(map(str, paths))}: no finished job ({len(unfinished)} "
                                "running or failed)")
    # a job's group: its model's name and the overrides that not every job shares (besides model=
    # itself)
    common = set.intersection(*(set(j["overrides"]) for j in jobs)) if jobs else set()
    for job in jobs if by_overrides else ():
        own = sorted(o for o in set(job["overrides"]) - common if not o.startswith("model="))
        job["model"] = job["model"] + (f" [{' '.join(own)}]" if own else "")
    rename = rename or {}
    if unknown := sorted(rename.keys() - {j["model"] for j in jobs}):
        raise ValueError(f"--rename {unknown[0]}=...: no job is labelled {unknown[0]!r}; the "
                         f"labels: {sorted({j['model'] for j in jobs})}")
    for job in jobs:
        job["model"] = rename.get(job["model"], job["model"])
    jobs += [job for spec in borrowed for job in recorded_jobs(spec, metrics)]
    seen: dict[tuple[str, int], str] = {}
    # a record pairs by model and seed: two jobs there would make one of them vanish
    for job in jobs:
        if (other := seen.setdefault((job["model"], job["seed"]), job["folder"])) != job["folder"]:
            raise ValueError(f"two jobs of model {job['model']!r} with seed {job['seed']}: {other} "
                             f"and {job['folder']}; a record keeps one job per model and seed: "
                             "record them apart, or tell them apart by an override (without "
                             "--by-name)")
    if baseline is not None and baseline not in {job["model"] for job in jobs}:
        raise ValueError(f"--baseline {baseline}: no job of that model (models: "
                         f"{sorted({job['model'] for job in jobs})})")
    by_model: dict[str, dict[str, dict[int, float]]] = {}
    for job in jobs:
        for k, v in job["metrics"].items():
            if v is not None and not math.isnan(v):
                by_model.setdefault(job["model"], {}).setdefault(k, {})[job["seed"]] = v
            else:  # asked for and empty (NaN: e.g. no agent reached the horizon): said, not hidden
                log.warning("%s: %s is NaN (no data); left out of model %s's mean over seeds",
                            job["folder"], k, job["model"])
    models = {}
    for name, per_metric in by_model.items():
        models[name] = {k: summary(list(v.values())) for k, v in per_metric.items()}
        if baseline is not None and name != baseline and baseline in by_model:
            for k, v in per_metric.items():
                if (diff := paired(v, by_model[baseline].get(k, {}))) is not None:
                    models[name][k]["vs_" + baseline] = diff
    return {"command": command, "baseline": baseline, "models": models, "jobs": jobs,
            "unfinished": unfinished}


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m dider.analysis.record",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="*", type=Path, help="sweep folders or run folders")
    parser.add_argument("--out", type=Path, required=True, help="the JSON file to write")
    parser.add_argument("--baseline", help="a model name: differences paired by seed against it")
    parser.add_argument("--command", help="the command that ran the sweeps (kept in the record)")
    parser.add_argument("--metric", action="append",
                        help="a metric to keep (repeatable; default: a standard set)")
    parser.add_argument("--label", default="name",
                        help="the model config key that names a job's model (default: name)")
    parser.add_argument("--curve", action="append", default=[], help="a training or validation "
                        "metric to keep over the epochs, from each job's CSV log (repeatable)")
    parser.add_argument("--by-name", action="store_true", help="group jobs by their model's name "
                        "alone, not by the overrides that differ between them (sweeps of one "
                        "configuration run apart)")
    parser.add_argument("--rename", action="append", default=[], metavar="LABEL=NEW",
                        help="record the jobs labelled LABEL as NEW (repeatable; two spellings of "
                        "one configuration merge)")
    parser.add_argument("--jobs-from", action="append", default=[], metavar="RECORD:MODEL",
                        help="a model's jobs from a committed record, as recorded (repeatable)")
    args = parser.parse_args(argv)
    if not args.paths and not args.jobs_from:
        parser.error("give sweep or run folders, or --jobs-from RECORD:MODEL")
    if bad := [r for r in args.rename if "=" not in r]:
        parser.error(f"--rename {bad[0]}: expected LABEL=NEW")
    rename = dict(r.rsplit("=", 1) for r in args.rename)
    record = build(args.paths, args.metric or DEFAULT_METRICS, args.baseline, args.command,
                   args.label, by_overrides=not args.by_name, curves=args.curve, rename=rename,
                   borrowed=args.jobs_from)
    atomic_write_text(args.out, json.dumps(record, indent=1))
    for name, per_metric in record["models"].items():
        cells = [f"{k.removeprefix('test/')} {v['mean']:.4g}" for k, v in per_metric.items()
                 if k in ("test/mse/h15", "test/mse/h25", "test/segments/steps_per_segment")]
        print(f"{name:24s} n={max(v['n'] for v in per_metric.values())}  " + "  ".join(cells))
    return record


if __name__ == "__main__":
    main()
