"""dider: relational inference of dynamically evolving interactions (DIDER, DNRI, NRI).

``dider.load(run_or_checkpoint)`` gives a trained model for new data (:mod:`dider.trained`);
``dider.pretrained()`` lists the trained models shipped with the package, each loaded by its name
(``dider.load("synth/dider")``)."""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    # Lazily, so that `import dider` (and reading its version) stays free of torch.
    if name in ("load", "TrainedModel"):
        from dider import trained

        return getattr(trained, name)
    if name == "pretrained":
        from dider.shipped import pretrained

        return pretrained
    raise AttributeError(f"module 'dider' has no attribute {name!r}")
