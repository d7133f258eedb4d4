"""The resolvers the app's configs use (``${dider_job_name:...}``, ``${dider_precision:...}``,
``${kloppy_sample:...}``): registered when the config package ``dider.conf`` is imported, so the
configs compose wherever Hydra reads them (the app, the search, ``hydra.compose`` in a notebook or a
test)."""

from __future__ import annotations

import hashlib
import os

from omegaconf import OmegaConf

from dider.perf import native_bf16, trains_on_cpu
from dider.validation import ConfigError


def job_name(override_dirname: str, limit: int = 120) -> str:
    """A sweep job's folder name: its overrides, shortened with a stable hash when too long for a
    path."""
    name = override_dirname.replace("/", "_") or "default"
    if len(name) <= limit:
        return name
    digest = hashlib.sha256(name.encode()).hexdigest()[:10]
    return f"{name[: limit - 12]}__{digest}"


# What $DIDER_DEFAULT_PRECISION may say (Lightning's precision names).
PRECISIONS = ("64-true", "32-true", "16-mixed", "bf16-mixed", "16-true", "bf16-true")


def default_precision(accelerator: str | None) -> str:
    """``trainer.precision``'s default: bf16 autocast where training runs on a CPU that computes
    bf16 natively (AVX-512-BF16 or AMX: the synthetic DNRI step 1.85x as fast, the metrics within
    the seed spread; docs/performance.md), fp32 elsewhere (GPUs: not measured here).
    ``$DIDER_DEFAULT_PRECISION`` replaces the choice for a whole environment (the test suite sets
    32-true: its thresholds were measured in fp32)."""
    pinned = os.environ.get("DIDER_DEFAULT_PRECISION")
    if pinned:
        if pinned not in PRECISIONS:
            raise ConfigError(f"DIDER_DEFAULT_PRECISION={pinned!r}: expected one of "
                              f"{list(PRECISIONS)}")
        return pinned
    return "bf16-mixed" if trains_on_cpu(accelerator) and native_bf16("cpu") else "32-true"


def kloppy_sample(name: str) -> str:
    """``${kloppy_sample:NAME}``: :func:`dider.data.readers.kloppy.kloppy_sample`, imported when a
    config uses it (composing a config loads neither the data modules nor Lightning)."""
    from dider.data.readers.kloppy import kloppy_sample as find

    return find(name)


def register_resolvers() -> None:
    """Registers (or re-registers) every resolver the configs use."""
    for name, resolver in {"dider_job_name": job_name, "dider_precision": default_precision,
                           "kloppy_sample": kloppy_sample}.items():
        OmegaConf.register_new_resolver(name, resolver, replace=True)
