"""Aggregate a Hydra sweep into tables and plots: `python -m dider.analysis.report multirun/SWEEP [--out DIR]`.

Reads every job's metrics.json, groups the jobs by model (and num_edges, or any other swept setting,
when it varies), and writes to DIR (default: the sweep folder) report.md and report.csv (mean ±
sample std over the seeds), runs.csv (one row per job: its swept settings and metrics), horizons.png
(forecast MSE by horizon with 95% confidence bands, Student's t), edge_ablation.png (when num_edges
varies) and one job's timeline figures per group. Failed jobs (a .hydra/ folder without a readable
metrics.json) and missing ones (combinations that multirun.yaml's sweep expects but no folder holds)
are listed, never dropped silently.
"""

from __future__ import annotations

import argparse
import io
import itertools
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from hydra.core.override_parser.overrides_parser import OverridesParser  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from dider.analysis.record import read_job  # noqa: E402
from dider.analysis.report_latex import latex_table  # noqa: E402
from dider.analysis.report_table import (  # noqa: E402
    BEST_NOTE,
    add_ratios,
    group_stats,
    jobs_frame,
    marked_cells,
    paired_support,
)
from dider.io import atomic_write_bytes, atomic_write_text  # noqa: E402

log = logging.getLogger(__name__)

SECTIONS = (("Forecast against constant velocity: ADE over constant velocity's, same clips", r"ade_vs_cv/h\d+$"),
            ("Forecast against DNRI: error over DNRI's, paired by seed", r"(ade|fde)_vs_dnri/h\d+$"),
            ("Forecast against the same model with every edge off: ADE over the edge-free roll-out's",
             r"ade_vs_no_edges/h\d+$"),
            ("Sampled futures: the best of K per agent (data units)", r"(min_ade|min_fde|miss_rate)_\d+/h\d+$"),
            ("Displacement error of the forecast positions (data units)", r"(cv/)?(ade|fde)/h\d+$"),
            ("Forecast MSE (normalised units)", r"mse/h\d+$"), ("Forecast MSE (data units)", r"mse_raw/h\d+$"),
            ("Forecast MSE with the edges inferred from the whole clip", r"mse_posterior/h\d+$"),
            ("Forecast MSE with the ground-truth edges", r"mse_oracle/h\d+$"),
            ("Edge accuracy", r"edge_acc/"),
            ("Duration slots: the model's own cut", r"segments/"),
            ("Segments", r"(segments_per_edge|switches_per_100|boundary_f1|run_length/\w+|interaction_rate/\w+)$"),
            ("What each edge type means (data units; others: the other edge-steps)", r"type\d+/"),
            ("Consistency", r".*consist"), ("Losses", r"(nll|kl_edge|kl_duration|sparsity|prior_fit|nelbo)$"),
            ("Other", r""))
NOT_GROUPED = {"seed", "model", "model.num_edges"}  # model and num_edges are read from each job's record


@dataclass
class Group:
    key: dict[str, Any]
    jobs: list[dict[str, Any]] = field(default_factory=list)  # metrics.json records, with "dir" added

    @property
    def label(self) -> str:
        return " ".join([str(self.key["model"])] + [f"{k}={v}" for k, v in self.key.items() if k != "model"])


@dataclass
class Summary:
    groups: list[Group]
    metrics: list[str]
    failed: list[str]
    missing: list[str]
    expected: int | None
    ignored: list[str] = field(default_factory=list)  # job folders whose overrides the sweep never launched

    @property
    def keys(self) -> list[str]:
        """The columns that name a group (model first, then num_edges and the other swept settings)."""
        return list(dict.fromkeys(k for g in self.groups for k in g.key))

    @cached_property
    def frame(self) -> pd.DataFrame:
        """One row per finished job: its group, the group's key, its seed and every metric."""
        return jobs_frame(self.groups, self.metrics)

    @cached_property
    def stats(self) -> pd.DataFrame:
        """Per group: mean, std, n and the 95% half-width of every metric (columns (metric, stat))."""
        return group_stats(self.frame, self.metrics)


def _canon(overrides: Sequence[str]) -> frozenset[str]:
    """Overrides as the sweeper renders them (key=value), order-free, to match jobs against the sweep."""
    parsed = OverridesParser.create().parse_overrides(list(overrides))
    return frozenset(f"{o.get_key_element()}={o.get_value_element_as_str()}" for o in parsed)


def expected_jobs(sweep: Path) -> list[frozenset[str]] | None:
    """The override sets the basic sweeper launches for multirun.yaml (None: no file or another sweeper)."""
    path = sweep / "multirun.yaml"
    if not path.exists():
        return None
    hydra_cfg = OmegaConf.load(path).hydra
    if "BasicSweeper" not in str(hydra_cfg.sweeper.get("_target_", "")):
        return None
    lines = ([f"{k}={v}" for k, v in (hydra_cfg.sweeper.get("params") or {}).items()]
             + list(hydra_cfg.overrides.task))
    # The basic sweeper's job list: the Cartesian product of every swept key's values, a later
    # setting of a key (the command line) replacing an earlier one (the config's sweeper params).
    choices: dict[str, list[str]] = {}
    for o in OverridesParser.create().parse_overrides(lines):
        key = o.get_key_element()
        values = list(o.sweep_string_iterator()) if o.is_sweep_override() else [o.get_value_element_as_str()]
        choices.pop(key, None)
        choices[key] = [f"{key}={v}" for v in values]
    return [_canon(job) for job in itertools.product(*choices.values())]


def collect(sweep: Path) -> tuple[list[dict[str, Any]], list[str], list[str], int | None, list[str]]:
    """(records of finished jobs in sweep order, failed or running job folders with the reason, missing override
    sets, expected count, ignored job folders: runs whose overrides are not among the sweep's jobs, e.g. copied in).
    A job's own evaluations (``eval/<name>/`` inside it) are not jobs of the sweep."""
    dirs = {p.parent for p in sweep.rglob(".hydra") if p.is_dir()} | {p.parent for p in sweep.rglob("metrics.json")}
    dirs = {d for d in dirs if not any(parent in dirs for parent in d.parents)}
    records, failed, found = [], [], set()
    for d in sorted(dirs):
        overrides_file = d / ".hydra" / "overrides.yaml"
        overrides = list(OmegaConf.load(overrides_file)) if overrides_file.exists() else None
        record, state = read_job(d)
        if record is None:
            log.warning("%s: %s; left out of the report", d, state)
            failed.append(f"{d.relative_to(sweep)} ({state.removeprefix('failed: ')})")
            found.add(_canon(overrides or []))
            continue
        record["dir"], record["_key"] = d, _canon(overrides if overrides is not None else record.get("overrides", []))
        records.append(record)
        found.add(record["_key"])
    _warn_twins(records, sweep)
    expected = expected_jobs(sweep)
    if expected is None:
        return records, failed, [], None, []
    jobs = set(expected)
    ignored = [f"{r['dir'].relative_to(sweep)} (its overrides are not a job of this sweep)" for r in records
               if r["_key"] not in jobs]
    records = [r for r in records if r["_key"] in jobs]
    swept = set.union(set(), *(e - expected[0] for e in expected))  # the key=value pairs that vary
    swept_keys = {kv.split("=", 1)[0] for kv in swept}
    missing = [",".join(sorted(kv for kv in e if kv.split("=", 1)[0] in swept_keys or not swept_keys))
               for e in expected if e not in found]
    order = {e: i for i, e in enumerate(expected)}  # the sweep's order (models as listed, num_edges ascending)
    records.sort(key=lambda r: order.get(r["_key"], len(order)))
    return records, failed, missing, len(expected), ignored


def _warn_twins(records: list[dict[str, Any]], sweep: Path) -> None:
    """Two finished jobs with the same overrides (a job run twice, copied in): both stay in the
    tables, each a row of runs.csv, and the warning names them (a ratio to the baseline is then
    ambiguous and left out)."""
    by_key: dict[frozenset[str], list[str]] = {}
    for r in records:
        by_key.setdefault(r["_key"], []).append(str(r["dir"].relative_to(sweep)))
    for folders in by_key.values():
        if len(folders) > 1:
            log.warning("jobs %s ran the same settings: both are kept in the report's rows and statistics",
                        ", ".join(folders))


def group_jobs(records: list[dict[str, Any]], sweep: Path) -> list[Group]:
    """Group by model, num_edges when it varies, and any other swept override that varies (never seed)."""
    exclude = set(NOT_GROUPED)
    if (sweep / "multirun.yaml").exists():
        exclude |= set(OmegaConf.select(OmegaConf.load(sweep / "multirun.yaml"),
                                        "hydra.job.config.override_dirname.exclude_keys", default=[]) or [])
    settings = [{k: v for k, v in (kv.split("=", 1) for kv in r["_key"])
                 if k.lstrip("+~") not in exclude and not k.startswith("hydra.")} for r in records]
    edges = [r.get("config", {}).get("model", {}).get("num_edges") for r in records]
    varying = sorted({k for s in settings for k in s if len({s.get(k) for s in settings}) > 1})
    groups: dict[tuple, Group] = {}
    for record, setting, e in zip(records, settings, edges, strict=True):
        key = {"model": record.get("model", "?")}
        if len(set(edges)) > 1:
            key["num_edges"] = e
        key |= {k: setting.get(k) for k in varying}
        groups.setdefault(tuple(key.items()), Group(key)).jobs.append(record)
    return list(groups.values())


def _section(metric: str) -> int:
    name = metric.removeprefix("test/")
    return next(i for i, (_, pattern) in enumerate(SECTIONS) if re.match(pattern, name))


def _order(metric: str) -> tuple:
    horizon = re.search(r"/h(\d+)$", metric)
    return _section(metric), int(horizon.group(1)) if horizon else 0, metric


def summarise(sweep: Path) -> Summary:
    """The sweep's finished jobs in groups, with the ratios to DNRI added when DNRI is in the sweep."""
    records, failed, missing, expected, ignored = collect(sweep)
    groups = group_jobs(records, sweep)
    add_ratios(groups)
    metrics = sorted({k for r in records for k, v in r["metrics"].items()
                      if k.startswith("test/") and isinstance(v, (int, float))}, key=_order)
    return Summary(groups, metrics, failed, missing, expected, ignored)


def _save(fig: plt.Figure, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def horizons_figure(s: Summary, path: Path) -> bool:
    """Forecast MSE against horizon per group: the mean with a 95% confidence band for it (mean ± t
    std / sqrt(n), Student's t with n-1 degrees of freedom; no band for a single job)."""
    mse = [m for m in s.metrics if re.fullmatch(r"test/mse/h\d+", m)]
    if not mse:
        return False
    fig, ax = plt.subplots(figsize=(6, 4))
    hs = np.array([int(m.rsplit("h", 1)[1]) for m in mse])
    for i, g in enumerate(s.groups):
        mean, half, n = (s.stats.loc[i, [(m, x) for m in mse]].to_numpy(float) for x in ("mean", "ci95", "n"))
        half = np.nan_to_num(half)  # one job: no band
        ax.plot(hs, mean, marker="o", label=f"{g.label} (n={int(n.max())})")
        # on the log axis a band reaching 0 would span decades: its lower edge stops at a tenth of the mean
        ax.fill_between(hs, np.maximum(mean - half, mean / 10), mean + half, alpha=0.2)
    ax.set(xlabel="forecast horizon (steps after burn-in)", ylabel="MSE (normalised)", yscale="log")
    # two lines, each narrower than the figure: a one-line title of this length is cut at both edges
    ax.set_title("Forecast error by horizon\n95% confidence bands (lower edge at most 10x below the mean)",
                 fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    _save(fig, path)
    return True


def ablation_figure(s: Summary, path: Path) -> list[str]:
    """MSE against num_edges per horizon (error bars: std over seeds), drawn only when some model
    was run with several num_edges (not for tables whose models merely differ in it). Returns the
    best-e lines."""
    mse = [m for m in s.metrics if re.fullmatch(r"test/mse/h\d+", m)]
    rows: dict[str, list[Group]] = {}
    for g in s.groups:
        if "num_edges" in g.key:
            rows.setdefault(" ".join(f"{k}={v}" for k, v in g.key.items() if k != "num_edges"), []).append(g)
    rows = {name: sorted(gs, key=lambda g: g.key["num_edges"]) for name, gs in rows.items() if len(gs) > 1}
    if not mse or not rows:
        return []
    fig, axes = plt.subplots(1, len(mse), figsize=(4 * len(mse), 3.5), squeeze=False)
    best = []
    for ax, m in zip(axes[0], mse, strict=True):
        for name, gs in rows.items():
            e = [g.key["num_edges"] for g in gs]
            at = [s.groups.index(g) for g in gs]
            mean, std = (s.stats.loc[at, (m, x)].to_numpy(float) for x in ("mean", "std"))
            ax.errorbar(e, mean, yerr=np.nan_to_num(std), marker="o", capsize=3, label=name)
            i = int(np.nanargmin(mean))
            best.append(f"{name}, {m.removeprefix('test/')}: lowest mean MSE at num_edges={e[i]}"
                        + paired_caveat(gs, i, m))
        ax.set(xlabel="num_edges", ylabel="MSE (normalised)", title=m.removeprefix("test/"), yscale="log")
        ax.set_xticks(sorted({g.key["num_edges"] for gs in rows.values() for g in gs}))
        ax.legend(fontsize=7)
    fig.tight_layout()
    _save(fig, path)
    return best


def paired_caveat(groups: list[Group], best: int, metric: str) -> str:
    """Whether group ``best``'s lower ``metric`` holds against every other group, paired by seed: the 95%
    Student-t interval of the per-seed differences lies below 0. -> a note for the claim's line."""
    supported, n, other = paired_support(jobs_frame(groups, [metric]), best, metric)
    if not supported:
        return (f", not established: paired over {n} seed(s), the 95% interval of its difference "
                f"to num_edges={groups[other].key['num_edges']} reaches 0")
    return f" (paired over {n} seeds, 95%)"


def copy_timelines(s: Summary, out: Path) -> list[tuple[str, str, list[str]]]:
    """One job's timeline figures per group (its lowest seed): (group, job folder, copied paths rel. to out)."""
    shown = []
    for g in s.groups:
        for job in sorted(g.jobs, key=lambda j: j.get("seed", 0)):
            pngs = sorted((Path(job["dir"]) / "figures").glob("timeline_*.png"))
            if pngs:
                slug = re.sub(r"[^A-Za-z0-9_.=-]+", "_", g.label)
                for p in pngs:
                    atomic_write_bytes(out / "timelines" / slug / p.name, p.read_bytes())
                shown.append((g.label, Path(job["dir"]).name, [f"timelines/{slug}/{p.name}" for p in pngs]))
                break
    return shown


def write_csv(s: Summary, path: Path) -> None:
    """One row per group: its key, n (jobs), seeds, and each metric's mean, std and 95% half-width."""
    table = pd.DataFrame({k: [g.key.get(k) for g in s.groups] for k in s.keys})
    table["n"] = [len(g.jobs) for g in s.groups]
    table["seeds"] = [";".join(str(j.get("seed")) for j in g.jobs) for g in s.groups]
    stats = {f"{m}_{x}": s.stats[(m, x)].to_numpy() for m in s.metrics for x in ("mean", "std", "ci95")}
    atomic_write_text(path, pd.concat([table, pd.DataFrame(stats)], axis=1).to_csv(index=False))


def write_runs_csv(s: Summary, sweep: Path, path: Path) -> None:
    """One row per finished job: its folder, model, seed, swept settings (the overrides of its
    command line) and every test metric, a tidy table for pandas and plotting."""
    jobs = [j for g in s.groups for j in g.jobs]
    settings = list(dict.fromkeys(o.split("=", 1)[0] for j in jobs for o in j.get("overrides", []) if "=" in o))
    settings = [k for k in settings if k not in ("model", "seed")]
    given = [dict(o.split("=", 1) for o in j.get("overrides", []) if "=" in o) for j in jobs]
    table = pd.DataFrame({"job": [str(Path(j["dir"]).relative_to(sweep)) for j in jobs],
                          "model": [j.get("model") for j in jobs], "seed": [j.get("seed") for j in jobs],
                          **{k: [g.get(k, "") for g in given] for k in settings}})
    metrics = s.frame[s.metrics].reset_index(drop=True)  # the frame holds the jobs in the same order
    atomic_write_text(path, pd.concat([table, metrics], axis=1).to_csv(index=False))


def markdown(s: Summary, sweep: Path, figures: list[str], best: list[str], timelines: list) -> str:
    n_ok = sum(len(g.jobs) for g in s.groups)
    lines = [f"# Sweep report: `{sweep}`", "",
             f"{n_ok} finished jobs, {len(s.failed)} failed, {len(s.missing)} missing"
             + (f" (the sweep expects {s.expected})." if s.expected is not None else "."),
             f"Cells: mean ± sample std (n-1) over the seeds of a row, n = jobs in the row; {BEST_NOTE}.", ""]
    keys = s.keys
    for i, (title, _) in enumerate(SECTIONS):
        cols = [m for m in s.metrics if _section(m) == i]
        if not cols:
            continue
        # one family per horizon (mse/h01, mse/h15...): the horizons name the columns; else the whole names
        by_horizon = len({m.rsplit("/", 1)[0] for m in cols}) == 1 and all(
            re.fullmatch(r"h\d+", m.rsplit("/", 1)[-1]) for m in cols)
        columns = [marked_cells(s.stats, s.frame, m, ("**", "**"), "†") for m in cols]
        names = [fmt.header(m.rsplit("/", 1)[-1] if by_horizon else m.removeprefix("test/"))
                 for m, (fmt, _) in zip(cols, columns, strict=True)]
        lines += [f"## {title}", "", "| " + " | ".join([*keys, "n", *names]) + " |",
                  "|" + "---|" * (len(keys) + 1 + len(cols))]
        for i, g in enumerate(s.groups):
            cells = [mean + (f" ± {std}" if std else "") for mean, std in (c[1][i] for c in columns)]
            lines.append("| " + " | ".join([*(str(g.key.get(k)) for k in keys), str(len(g.jobs)), *cells]) + " |")
        lines.append("")
    if figures:
        lines += ["## Figures", "", *(f"![{f}]({f})" for f in figures), ""]
        lines += [*(f"- {b}" for b in best), ""] if best else []
    if timelines:
        lines += ["## Interaction timelines (one job per row)", ""]
        for label, job, paths in timelines:
            lines += [f"**{label}** (`{job}`)", "", *(f"![{label}]({p})" for p in paths), ""]
    lines += ["## Failed, missing or ignored jobs", "", "(failed: a job folder without a readable "
              "metrics.json, with why, or one still running; missing: swept values that no job "
              "folder holds; ignored: a finished run whose overrides are not a job of this sweep, "
              "e.g. copied in, left out of the tables)", ""]
    lines += ([f"- failed: `{f}`" for f in s.failed] + [f"- missing: `{m}`" for m in s.missing]
              + [f"- ignored: `{i}`" for i in s.ignored]) or ["none"]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> Summary:
    parser = argparse.ArgumentParser(prog="python -m dider.analysis.report", description=__doc__.splitlines()[0])
    parser.add_argument("sweep", type=Path, help="a multirun folder (multirun/<date>/<time>)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: the sweep folder)")
    args = parser.parse_args(argv)
    sweep: Path = args.sweep
    if not sweep.is_dir():
        parser.error(f"{sweep}: not a folder")
    out: Path = args.out or sweep
    out.mkdir(parents=True, exist_ok=True)
    s = summarise(sweep)
    figures = ["horizons.png"] if horizons_figure(s, out / "horizons.png") else []
    best = ablation_figure(s, out / "edge_ablation.png")
    figures += ["edge_ablation.png"] if best else []
    text = markdown(s, sweep, figures, best, copy_timelines(s, out))
    atomic_write_text(out / "report.md", text)
    write_csv(s, out / "report.csv")
    atomic_write_text(out / "report.tex", latex_table(s))
    write_runs_csv(s, sweep, out / "runs.csv")
    print(text)
    print(f"report: {out / 'report.md'}  table: {out / 'report.csv'} (LaTeX: "
          f"{out / 'report.tex'})  per job: {out / 'runs.csv'}")
    if s.failed or s.missing or s.ignored:
        print(f"warning: {len(s.failed)} failed, {len(s.missing)} missing and {len(s.ignored)} "
              "ignored job folders (listed in the report)")
    return s


def cli() -> None:
    """The console script (``dider-report``): ``main`` without its return value (an exit status of 0)."""
    main()


if __name__ == "__main__":
    main()
