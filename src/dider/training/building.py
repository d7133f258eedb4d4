"""The parts a model config builds for the LightningModule
(:class:`~dider.training.module.RelationalVAEModule`): the network, the optimiser's and scheduler's
factories, the forecast protocol and the module's own settings, each class checked and built where
its kind goes (:mod:`dider.targets`), with the plain config that checkpoints keep."""

from __future__ import annotations

from collections.abc import Collection, Mapping
from typing import Any

import torch
from omegaconf import DictConfig

from dider.models.checkpoint_format import network_config
from dider.models.inference import plain_config
from dider.settings import ForecastProtocol
from dider.targets import build, named_targets
from dider.validation import ConfigError, node_problems

# the optimiser of a config that names none
ADAM = {"_target_": "torch.optim.Adam", "_partial_": True}
# The keys of a model config's top level that the module takes (``name`` and ``num_edges`` are the
# network's, which ``net`` interpolates so that users type ``model.num_edges``).
SETTINGS = ("net", "protocol", "optimizer", "scheduler", "eval_seed", "check_finite")


def module_parts(cfg: DictConfig | Mapping[str, Any], trust: Collection[str] | None = None,
                 net: torch.nn.Module | None = None) -> dict[str, Any]:
    """The constructor's arguments for a model config (``cfg.model``). trust: None when the config
    is the caller's own (every class it names may be built), else the user's classes a file's config
    may build beside dider's. net: the network its ``net`` node describes, already built (a loaded
    model's), else built here."""
    node = plain_config(cfg)
    # a checkpoint's too: nothing dropped unread
    if stray := sorted(set(node) - {*SETTINGS, "name", "num_edges"}):
        raise ConfigError(f"model config: {', '.join(stray)}: not a setting of the model's top "
                          f"level ({', '.join(SETTINGS)}, name, num_edges)")
    trust = (named_targets([node.get(k) for k in ("net", "optimizer", "scheduler")])
             if trust is None else trust)
    if problems := node_problems(ForecastProtocol, node.get("protocol"), "model.protocol"):
        raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(problems))
    where = "model config"
    parts = {"net": net if net is not None else build(network_config(node), "network", where,
                                                      "model.net", trust),
             "protocol": ForecastProtocol(**node["protocol"]),
             "optimizer": build(node.get("optimizer") or ADAM, "optimizer", where,
                                "model.optimizer", trust),
             "config": {k: node[k] for k in SETTINGS if k in node}}
    if node.get("scheduler") is not None:
        parts["scheduler"] = build(node["scheduler"], "scheduler", where, "model.scheduler", trust)
    return parts | {k: node[k] for k in ("eval_seed", "check_finite") if k in node}
