"""Ship a trained run inside the package: a slim copy of its checkpoint and a catalog record of how
it was trained and what it scores, so that ``dider.load(NAME)`` and ``ckpt_path=NAME`` find it.

    python -m dider.analysis.ship RUN synth/dider --what "DIDER, synthetic protocol, seed 1" \\
        --evaluate experiment=synth_protocol model=dider data.num_test=100

The evaluation command (``mode=eval ckpt_path=NAME`` and the given overrides) runs here, in a fresh
process, and its test metrics go into the record; the shipped test (tests/test_shipped.py) runs it
again and compares. When a change of the evaluation's defaults changes what a shipped model scores,
``--rescore NAME`` runs its recorded command again and records the new metrics (the checkpoint and
how it was trained stay):

    python -m dider.analysis.ship --rescore synth/dider
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from dider.io import atomic_torch_save, atomic_write_text, read_run_record
from dider.shipped import HERE, catalog
from dider.targets import check
from dider.trained import find_checkpoint, read_checkpoint

# Overrides that say where and how a run wrote, not what it trained: left out of the recorded
# command.
WHERE = ("hydra.", "logger=", "trainer.enable_progress_bar=", "threads=", "ckpt_path=")

# What a checkpoint needs to be loaded for testing, prediction and the API; the optimiser and loop
# states stay behind.
KEPT = ("state_dict", "hyper_parameters", "dider", "pytorch-lightning_version", "epoch",
        "global_step")


def slim(source: Path) -> dict[str, Any]:
    """The checkpoint at ``source`` without its optimiser, scheduler, callback and loop states; its
    model config checked as every door that loads it checks it (only dider's classes: what the
    package ships, anyone loads)."""
    ckpt = read_checkpoint(source)
    check(ckpt["hyper_parameters"], "module", source, "hyper_parameters")
    return {k: ckpt[k] for k in KEPT if k in ckpt}


def evaluate(name: str, overrides: list[str]) -> dict[str, float]:
    """The test metrics of ``python -m dider.run mode=eval ckpt_path=NAME OVERRIDES`` (a fresh
    process)."""
    with tempfile.TemporaryDirectory() as folder:
        cmd = [sys.executable, "-m", "dider.run", "mode=eval", f"ckpt_path={name}", *overrides,
               "logger=csv",
               "hydra.mode=RUN", f"hydra.run.dir={folder}", "trainer.enable_progress_bar=false"]
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stderr[-3000:]}")
        return read_run_record(Path(folder) / "metrics.json")["metrics"]


def write_catalog(entries: dict[str, Any]) -> None:
    """The catalog with ``entries`` (atomically), read afresh by the next ``catalog()``."""
    catalog.cache_clear()
    atomic_write_text(HERE / "catalog.json", json.dumps(entries, indent=1, sort_keys=True) + "\n")
    catalog.cache_clear()


def ship(run: Path, name: str, what: str, overrides: list[str]) -> dict[str, Any]:
    """Write the slim checkpoint and its catalog record (both atomically); -> the record."""
    source = find_checkpoint(run)
    record_of_run = (read_run_record(run / "metrics.json") if (run / "metrics.json").is_file()
                     else {})
    file = name.replace("/", "_") + ".ckpt"
    atomic_torch_save(slim(source), HERE / file)
    entries = dict(catalog())
    entries[name] = {"file": file, "what": what,
                     "trained_with": "python -m dider.run " + " ".join(
                         o for o in record_of_run.get("overrides", []) if not o.startswith(WHERE)),
                     "git_commit": record_of_run.get("provenance", {}).get("git_commit"),
                     "evaluate": overrides, "metrics": {}}
    # how long its training took, and where: what a user's run that should match it will take
    provenance = record_of_run.get("provenance", {})
    entries[name] |= {k: provenance[v]
                      for k, v in (("trained_wall_s", "wall_s"), ("trained_device", "device"))
                      if v in provenance}
    write_catalog(entries)
    entries[name]["metrics"] = evaluate(name, overrides)
    write_catalog(entries)
    return entries[name]


def rescore(name: str) -> dict[str, Any]:
    """Score the shipped model ``name`` again with its recorded command and write the metrics into
    its record."""
    entries = dict(catalog())
    if name not in entries:
        raise SystemExit(f"--rescore: no shipped model {name!r} (shipped: "
                         f"{', '.join(sorted(entries))})")
    entries[name] = {**entries[name], "metrics": evaluate(name, entries[name]["evaluate"])}
    write_catalog(entries)
    return entries[name]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, nargs="?",
                        help="a trained run folder (or a checkpoint file)")
    parser.add_argument("name", nargs="?", help="the name to ship it under, e.g. synth/dider")
    parser.add_argument("--what", help="one line on what it is (required to ship)")
    parser.add_argument("--evaluate", nargs="*", default=[],
                        help="the overrides of its scoring command")
    parser.add_argument("--rescore", metavar="NAME",
                        help="score a shipped model again with its recorded command")
    args = parser.parse_args(argv)
    if args.rescore:
        record = rescore(args.rescore)
        print(f"{args.rescore}: {len(record['metrics'])} test metrics scored again")
        return
    if args.run is None or args.name is None or not args.what:
        parser.error("shipping needs RUN, NAME and --what (or --rescore NAME)")
    record = ship(args.run, args.name, args.what, args.evaluate)
    size = (HERE / record["file"]).stat().st_size
    print(f"{args.name}: {HERE / record['file']} ({size / 1e6:.2f} MB), {len(record['metrics'])} "
          "test metrics")


if __name__ == "__main__":
    main()
