"""The app's own config nodes besides the model and the data: the forecast protocol (``protocol``),
what ``mode=eval`` and ``mode=predict`` take (``eval``, ``predict``). Each is a dataclass: its
fields are the node's keys with their defaults and meaning, ``SETTINGS`` their rules. Its schema
(``schema/<Class>``) makes composition refuse a key it does not have where a config file sets one,
and the preflight refuses one added on the command line (``+predict.foo=1``), naming it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from omegaconf import MISSING

from dider.protocol import BURN_IN_MODES
from dider.validation import Rule, above, boolean, folder_name, integer, one_of, optional


@dataclass
class ForecastProtocol:
    """The forecast protocol (:mod:`dider.protocol`), which the model reads and checks against the
    clips (``conf/protocol``: one per data set; ``protocol=NAME`` picks another)."""

    burn_in: Any = MISSING  # frames observed before the roll-out
    horizons: Any = MISSING  # test horizons: steps after the burn-in, each <= clip length - burn_in
    # global: every agent observed for the clip's first burn_in frames; per_agent: each agent for
    # its own first burn_in present frames (agents that enter mid-clip)
    burn_in_mode: Any = "global"
    # sampled futures scored in every test pass: minADE_K / minFDE_K per horizon over K roll-outs
    # whose online edges are drawn from the prior (0: none)
    samples: Any = 6
    # data units: a sampled forecast's miss (minFDE_K above it; null: no miss rate)
    miss_threshold: Any = None

    SETTINGS: ClassVar[dict[str, Rule]] = {"burn_in": integer(1),
                                           "burn_in_mode": one_of(*BURN_IN_MODES),
                                           "samples": integer(0),
                                           "miss_threshold": optional(above(0))}


@dataclass
class EvalSettings:
    """``mode=eval``: test a checkpoint (``ckpt_path``: a checkpoint file, a run folder, or
    ``last``, the run folder's own)."""

    # An evaluation never writes over a training run: in a folder that holds one (ckpt_path=last, or
    # hydra.run.dir set to the run) it writes to eval/NAME there; null: the data config's name
    # (eval/synth, eval/table, ...).
    name: Any = None
    # the data's frame rate and downsampling (data.source.frame_rate, data.windows.downsample) shape
    # the features: left out, the checkpoint's are used; set to another value, evaluation stops
    # naming both, unless force is true.
    force: Any = False

    SETTINGS: ClassVar[dict[str, Rule]] = {"name": optional(folder_name), "force": boolean}


@dataclass
class PredictSettings:
    """``mode=predict``: what a checkpoint says about every clip of ``data``, written to
    ``predictions/``."""

    # A prediction never writes over a run: in a folder that holds one (checkpoints or a
    # metrics.json, e.g. hydra.run.dir set to the training run) it writes to predict/NAME there;
    # null: the data config's name.
    name: Any = None
    # also forecast this many steps after each clip's first burn_in frames (null: no)
    forecast_steps: Any = None
    # with forecast_steps: that many sampled futures of each clip too, their online edges drawn from
    # the prior (forecast.csv's rows of sample 1..K; sample 0 is the forecast itself); needs
    # forecast_steps
    samples: Any = 0
    burn_in: Any = None  # frames observed before the forecast (null: the model's burn_in)
    progress_s: Any = 30  # a progress line (clips done, time left) every this many seconds
    # the data's frame rate and downsampling (data.source.frame_rate, data.windows.downsample) shape
    # the features: left out, the checkpoint's are used; set to another value, prediction stops
    # naming both, unless force is true.
    force: Any = False

    SETTINGS: ClassVar[dict[str, Rule]] = {
        "name": optional(folder_name), "forecast_steps": optional(integer(1, " step")),
        "burn_in": optional(integer(1, " frame")), "progress_s": above(0), "force": boolean,
        "samples": integer(0),
    }


# The nodes, by the key that holds them.
NODES: dict[str, type] = {"protocol": ForecastProtocol, "eval": EvalSettings,
                          "predict": PredictSettings}
