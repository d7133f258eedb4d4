"""A data module built from flat settings (as older configs wrote them), nested as today's config nests them."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from dider.data.clips import ClipsDataModule
from dider.data.legacy import nest_args

CONF = Path(__file__).resolve().parents[2] / "conf" / "data"
# The data sets of fixed-length clips by their config's name, and the module each was before they became one.
CLIP_SETS = {"synth": "dider.data.synth.SynthDataModule", "springs": "dider.data.nri.NRIDataModule",
             "charged": "dider.data.nri.NRIDataModule", "nri_files": "dider.data.nri.NRIDataModule",
             "dnri_files": "dider.data.dnri_files.DNRIFilesDataModule",
             "basketball": "dider.data.basketball.BasketballDataModule",
             "trajectories": "dider.data.trajectories.TrajectoryDataModule"}


def flat(data: type | str, **settings: Any) -> Any:
    """A data module built from ``settings`` given flat: the source's under ``data.source``, the cut's under
    ``windows``. ``data``: a data module's class, or the name of a data config of clips (``synth``, ``springs``, ...),
    whose YAML's own values (sizes, loader) come first."""
    if isinstance(data, type):
        return data(**nest_args(f"{data.__module__}.{data.__qualname__}", settings)[1])
    body = OmegaConf.load(CONF / f"{data}.yaml")
    body.pop("defaults")
    given = nest_args(CLIP_SETS[data], settings)[1]
    return ClipsDataModule(**OmegaConf.to_container(OmegaConf.merge(body, given), resolve=True))
