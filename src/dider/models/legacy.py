"""Model configs of older checkpoints and run folders, read as today's, so they keep loading for prediction and
resumed runs.

- Before the network was the model config's ``net`` node, one flat node held the network's settings and the
  LightningModule's (:data:`MODULE_KEYS`); checkpoints named the network's config ``model``.
- Before the objective was a config node, its loss settings sat at the top of the network's config
  (``nll_variance``, ``beta_edge``, ``sparsity_mix``, ...). They are rebuilt as the ``objective`` node that
  computes the same loss (exactly where no capacity is set; with a capacity the sparsity term now sits outside
  the edge KL's |KL - C|; a prior fit at full weight from the first step, ``prior_fit_warmup: false``, is gone:
  the fit ramps with the KL warm-up).
- Before the segment-end duration's prior read the held type, its config had no ``online_prior`` and no
  ``end_readout``: the prior read the past alone (``past``) and evaluation read the median end (``median``).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

import torch

log = logging.getLogger(__name__)
_OBJECTIVE = "dider.models.objective"
OLD_LOSS_KEYS = ("nll_variance", "beta_edge", "beta_duration", "capacity_edge", "capacity_duration", "capacity_ramp",
                 "kl_warmup", "sparsity_mix", "no_edge_prob", "sparsity_form", "segment_kl", "prior_fit",
                 "prior_fit_warmup")


# The keys of an older flat model config that configured the LightningModule, not the network.
MODULE_KEYS = ("optimizer", "scheduler", "burn_in", "horizons", "burn_in_mode", "eval_seed", "check_finite", "samples",
               "miss_threshold")


def split_model_config(node: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """(the network's config, the LightningModule's settings) of a plain model config: today's, whose network
    is its ``net`` node, an older flat one (every key but :data:`MODULE_KEYS` the network's), or a network's
    config alone. The network's comes upgraded (:func:`upgrade_model_config`)."""
    module = {k: node[k] for k in MODULE_KEYS if k in node}
    if "net" not in node:
        return upgrade_model_config({k: v for k, v in node.items() if k not in MODULE_KEYS}), module
    if stray := stray_keys(node):
        raise ValueError("; ".join(stray))
    return upgrade_model_config(node["net"]), module


def stray_keys(node: Mapping[str, Any]) -> list[str]:
    """What is wrong with the top-level keys of a model config with a ``net`` node: a key that is neither the
    LightningModule's nor ``name`` / ``num_edges`` (a network setting written in the older flat layout, say,
    which would otherwise be ignored)."""
    known = {*MODULE_KEYS, "name", "num_edges", "net", "_target_"}
    return [f"model.{k}: not a setting of the model's top level ({sorted(known)}); the network's settings are "
            f"under model.net (model.net.{k})" for k in node if k not in known]


def network_hparams(hparams: Mapping[str, Any]) -> Mapping[str, Any] | None:
    """The network's config in a checkpoint's hyper-parameters (``net``; ``model`` in older ones), or None."""
    return hparams.get("net", hparams.get("model"))


# The segment-end duration's settings before its prior read the held type and evaluation read a decided end: what an
# older config that leaves them out meant.
SEGMENT_END = "dider.models.segment_end.SegmentEnd"
SEGMENT_END_BEFORE = {"end_readout": "median", "online_prior": "past"}


def upgrade_model_config(node: Mapping[str, Any]) -> dict[str, Any]:
    """A model config (plain, resolved) with its loss settings as an ``objective`` node; one that has it already
    is returned as it is. The old defaults fill settings an old config left out."""
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


def rename_likelihood(module: torch.nn.Module, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
    """A load_state_dict pre-hook: the likelihood's variance of older weights (``likelihood.variance``) is the
    objective's ``nll`` term's now."""
    if (old := f"{prefix}likelihood.variance") in state_dict:
        state_dict.setdefault(f"{prefix}objective.terms.nll.variance", state_dict.pop(old))
