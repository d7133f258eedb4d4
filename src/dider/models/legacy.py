"""Model configs of checkpoints written before the objective was a config node: their loss settings sat at the
top of the model config (``nll_variance``, ``beta_edge``, ``sparsity_mix``, ...). They are rebuilt as the
``objective`` node that computes the same loss (exactly where no capacity is set; with a capacity the sparsity
term now sits outside the edge KL's |KL - C|; a prior fit at full weight from the first step,
``prior_fit_warmup: false``, is gone: the fit ramps with the KL warm-up), so such checkpoints keep loading, for
prediction and resumed runs.
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


def upgrade_model_config(node: Mapping[str, Any]) -> dict[str, Any]:
    """A model config (plain, resolved) with its loss settings as an ``objective`` node; one that has it already
    is returned as it is. The old defaults fill settings an old config left out."""
    node = dict(node)
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
        objective["prior_fit"] = {"_target_": f"{_OBJECTIVE}.PriorFit", "weight": old["prior_fit"]}
        if not get("prior_fit_warmup", True) and get("kl_warmup", 0.0) > 0:
            log.warning("model.prior_fit_warmup=false of an older config is no longer an option: the prior fit "
                        "ramps with the KL warm-up (a resumed run's loss differs before the warm-up ends)")
    return node | {"objective": objective}


def rename_likelihood(module: torch.nn.Module, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
    """A load_state_dict pre-hook: the likelihood's variance of older weights (``likelihood.variance``) is the
    objective's ``nll`` term's now."""
    if (old := f"{prefix}likelihood.variance") in state_dict:
        state_dict.setdefault(f"{prefix}objective.terms.nll.variance", state_dict.pop(old))
