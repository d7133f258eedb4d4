"""What a dider checkpoint holds, its format number, and the one step that reads an older one as today's.

Every checkpoint dider writes records ``checkpoint["dider"]["format"]`` (:data:`FORMAT`). Where a checkpoint is
read (``dider.load``, ``mode=eval`` / ``predict``, a resumed run, ``RelationalVAEModule.load_from_checkpoint``,
``RelationalVAE.load_checkpoint``), :func:`upgrade` brings an older one to today's layout, once; a model built
from a config (a fresh run) never passes through it, and a new setting of a plugin or of the LightningModule is
added in its constructor's signature only.

Formats:

1. No number (everything written before it). Its layouts, all read as format 2:
   - the network's config named ``model`` in the hyper-parameters (today ``net``), and, older still, one flat node
     holding the network's settings and the LightningModule's (:data:`FLAT_MODULE_KEYS`);
   - the loss settings at the top of the network's config (``nll_variance``, ``beta_edge``, ``sparsity_mix``,
     ...), rebuilt as the ``objective`` node that computes the same loss (exactly where no capacity is set; with a
     capacity the sparsity term now sits outside the edge KL's |KL - C|; a prior fit at full weight from the first
     step, ``prior_fit_warmup: false``, is gone: the fit ramps with the KL warm-up);
   - a segment-end duration without ``online_prior`` and ``end_readout``: its prior read the past alone (``past``)
     and evaluation read the median end (``median``); its prior MLP kept as ``prior.0`` / ``prior.2``;
   - the likelihood's variance as ``likelihood.variance`` (today the objective's ``nll`` term's);
   - the network's weights at the top of the state dict (today under ``model.``).
2. Today's: ``net`` in the hyper-parameters, every plugin's settings as its constructor names them.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

log = logging.getLogger(__name__)

FORMAT = 2
_OBJECTIVE = "dider.models.objective"
SEGMENT_END = "dider.models.segment_end.SegmentEnd"
# A format-1 segment end's settings left out of its config: what they meant then.
SEGMENT_END_BEFORE = {"end_readout": "median", "online_prior": "past"}
OLD_LOSS_KEYS = ("nll_variance", "beta_edge", "beta_duration", "capacity_edge", "capacity_duration", "capacity_ramp",
                 "kl_warmup", "sparsity_mix", "no_edge_prob", "sparsity_form", "segment_kl", "prior_fit",
                 "prior_fit_warmup")
# The LightningModule's settings in a format-1 flat model config (the network's were the rest): the module's
# arguments when that layout was written, frozen here; a setting added since lives in the module's signature only.
FLAT_MODULE_KEYS = ("optimizer", "scheduler", "burn_in", "horizons", "burn_in_mode", "eval_seed", "check_finite",
                    "samples", "miss_threshold")


def format_of(checkpoint: Mapping[str, Any]) -> int:
    """The format a checkpoint was written in (1: before the number existed)."""
    return int((checkpoint.get("dider") or {}).get("format", 1))


def stamp(checkpoint: dict[str, Any], **fields: Any) -> None:
    """Mark a checkpoint being written as today's format, with what else dider keeps in it (``fields``)."""
    checkpoint["dider"] = {"format": FORMAT, **fields}


def upgrade(checkpoint: dict[str, Any], where: str | Path = "checkpoint") -> dict[str, Any]:
    """Bring a checkpoint (a loaded dict) to today's format, in place; returns it. A checkpoint of a newer format
    than this package reads is refused, naming ``where``."""
    marks = checkpoint.get("dider") or {}
    if not isinstance(marks, Mapping) or type(marks.get("format", 1)) is not int:
        raise ValueError(f"{where}: not a dider checkpoint (its format mark dider.format="
                         f"{(marks.get('format') if isinstance(marks, Mapping) else marks)!r} is no whole number)")
    found = format_of(checkpoint)
    if found > FORMAT:
        raise ValueError(f"{where}: written in checkpoint format {found} by a newer dider; this one reads formats "
                         f"up to {FORMAT}: upgrade the package")
    if found == FORMAT:
        return checkpoint
    hparams = checkpoint.get("hyper_parameters")
    net: Any = None
    if isinstance(hparams, dict):
        net = hparams.pop("model", None) if "net" not in hparams else hparams["net"]
        if isinstance(net, Mapping):
            module = {k: net[k] for k in FLAT_MODULE_KEYS if k in net}
            hparams["net"] = upgrade_network_config({k: v for k, v in net.items() if k not in FLAT_MODULE_KEYS})
            for key, value in module.items():
                hparams.setdefault(key, value)
            net = hparams["net"]
    if isinstance(state := checkpoint.get("state_dict"), dict):
        duration = (net or {}).get("duration") if isinstance(net, Mapping) else None
        checkpoint["state_dict"] = _upgrade_state(state, isinstance(duration, Mapping)
                                                  and duration.get("_target_") == SEGMENT_END)
    checkpoint.setdefault("dider", {})["format"] = FORMAT
    return checkpoint


def read(path: str | Path, **load: Any) -> dict[str, Any]:
    """A checkpoint file loaded (tensors and plain values only: ``weights_only``) and upgraded to today's format.
    ``load``: more of torch.load's arguments (``mmap``)."""
    checkpoint = torch.load(path, map_location="cpu", weights_only=True, **load)
    return upgrade(checkpoint, path) if isinstance(checkpoint, dict) else checkpoint


def network_config(node: Mapping[str, Any]) -> dict[str, Any]:
    """The network's config of a model config (``cfg.model``: its ``net`` node) or the network's config itself."""
    return dict(node["net"]) if "net" in node else dict(node)


def upgrade_network_config(node: Mapping[str, Any]) -> dict[str, Any]:
    """A format-1 network config (plain, resolved) as today's: its loss settings as an ``objective`` node, a
    segment end's settings it left out at what they meant then."""
    node = dict(node)
    duration = node.get("duration")
    if isinstance(duration, Mapping) and duration.get("_target_") == SEGMENT_END:
        node["duration"] = {**SEGMENT_END_BEFORE, **duration}
    if "objective" in node:
        return node
    old = {k: node.pop(k) for k in OLD_LOSS_KEYS if k in node}
    get = lambda key, default: old.get(key, default)  # noqa: E731
    mix, beta_edge = get("sparsity_mix", 0.0), get("beta_edge", 1.0)
    objective: dict[str, Any] = {
        "_target_": f"{_OBJECTIVE}.Objective", "kl_warmup": get("kl_warmup", 0.0),
        "capacity_ramp": get("capacity_ramp", 0.5),
        "nll": {"_target_": "dider.models.likelihood.GaussianNLL", "variance": get("nll_variance", 5e-5)},
        "kl_edge": {"_target_": f"{_OBJECTIVE}.EdgeKL", "weight": beta_edge * (1 - mix),
                    "capacity": get("capacity_edge", 0.0), "count": get("segment_kl", "per_segment")},
        "kl_duration": {"_target_": f"{_OBJECTIVE}.DurationKL", "weight": get("beta_duration", 1.0),
                        "capacity": get("capacity_duration", 0.0)},
    }
    if mix > 0:
        objective["sparsity"] = {"_target_": f"{_OBJECTIVE}.Sparsity", "weight": beta_edge * mix,
                                 "no_edge_prob": get("no_edge_prob", 0.9),
                                 "form": get("sparsity_form", "mean_edges"), "num_types": node.get("num_edges", 2)}
    if get("prior_fit", 0.0) > 0:
        objective["prior_fit"] = {"_target_": f"{_OBJECTIVE}.PriorFit", "weight": old["prior_fit"], "capacity": 0.0}
        if not get("prior_fit_warmup", True) and get("kl_warmup", 0.0) > 0:
            log.warning("model.prior_fit_warmup=false of an older config is no longer an option: the prior fit "
                        "ramps with the KL warm-up (a resumed run's loss differs before the warm-up ends)")
    return node | {"objective": objective}


def _upgrade_state(state: dict[str, Any], segment_end: bool) -> dict[str, Any]:
    """A format-1 state dict's keys as today's: the network under ``model.``, the variance as the ``nll`` term's,
    a segment end's (``segment_end``) past-only prior MLP as ``prior.past``."""
    if state and not any(k.startswith("model.") for k in state):
        state = {f"model.{k}": v for k, v in state.items()}
    out = {}
    for key, value in state.items():
        if key == "model.likelihood.variance":
            key = "model.objective.terms.nll.variance"
        elif segment_end and key.startswith(("model.duration.prior.0.", "model.duration.prior.2.")):
            key = "model.duration.prior.past." + key.removeprefix("model.duration.prior.")
        out[key] = value
    return out
