"""Trained models to start from, shipped inside the package: ``dider.load("synth/dider")``,
``ckpt_path=synth/dider``.

Each is a slim checkpoint (the weights, the model config, the data's normaliser and description; no
optimiser state) with a record of how it was trained and what it scores (``catalog.json``: the
training command and commit, and the evaluation command with its test metrics; the synthetic test
clips are regenerated from the data seed, so the command scores the same clips anywhere).
``dider.pretrained()`` lists them.
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent


@cache
def catalog() -> dict[str, dict[str, Any]]:
    """name -> its record: ``file`` (beside this module), ``what``, ``trained_with`` (the command),
    ``git_commit``, ``evaluate`` (the command that scores it), ``metrics`` (what that command gives)
    and, where known, ``trained_wall_s`` and ``trained_device`` (how long its training ran, and on
    what)."""
    return json.loads((HERE / "catalog.json").read_text())


def resolve(name: str | Path) -> Path | None:
    """The shipped checkpoint called ``name`` (e.g. ``synth/dider``), or None when none is."""
    record = catalog().get(str(name))
    return None if record is None else HERE / record["file"]


def pretrained() -> dict[str, str]:
    """The shipped trained models: name -> one line on what each is."""
    return {name: record["what"] for name, record in catalog().items()}


def unknown() -> str:
    """The end of an error for a name that is no file, folder or shipped model: what is shipped."""
    return f"nor a shipped model ({', '.join(catalog()) or 'none'})"
