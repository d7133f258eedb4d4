"""Every setting has a type rule: each scalar key of the model, data, protocol, eval and predict nodes (and the app's
own) given a value of the wrong type (a mapping) is refused by the preflight, naming the key, before any work."""

from __future__ import annotations

import copy

import pytest
from omegaconf import OmegaConf, open_dict

from dider.run import ConfigError, validate_config
from dider.training.overrides import dotted_keys

# Lightning's, the loggers' and Hydra's own settings, which those libraries check.
NOT_OURS = ("hydra", "trainer", "logger", "callbacks", "hparams_search", "debug", "output_dir", "edges_per_model")
CONFIGS = [["data=synth", "model=dider"], ["data=table", "data.source.path=/etc/hostname", "model=dnri"],
           ["data=ind", "data.source.root=/tmp", "model=nri"]]


def scalar_keys(cfg) -> list[str]:
    plain = OmegaConf.to_container(cfg, resolve=False)
    keys = []
    for key in dotted_keys(plain):
        if key.split(".")[0] in NOT_OURS or key.rsplit(".", 1)[-1] == "_target_":
            continue
        value = OmegaConf.select(cfg, key, throw_on_resolution_failure=False)
        raw = OmegaConf.select(OmegaConf.create(plain), key, throw_on_resolution_failure=False)
        if not OmegaConf.is_config(value) and not isinstance(value, list) and not (
                isinstance(raw, str) and raw.startswith("${")):  # interpolated copies: their source is walked
            keys.append(key)
    return keys


@pytest.mark.parametrize("overrides", CONFIGS, ids=[c[0] for c in CONFIGS])
def test_every_setting_refuses_a_wrong_type_naming_its_key(make_cfg, overrides):
    base = make_cfg(overrides, tiny=False)
    validate_config(base)  # the config itself passes
    keys = scalar_keys(base)
    assert len(keys) > 40
    unnamed, checked = [], 0
    for key in keys:
        cfg = copy.deepcopy(base)
        with open_dict(cfg):
            try:
                OmegaConf.update(cfg, key, {"x": 1}, merge=False)
            except Exception:  # the schema refuses the type itself, naming the key
                continue
        checked += 1
        try:
            validate_config(cfg)
            unnamed.append(f"{key}: passed")
        except ConfigError as e:
            if key not in str(e):
                unnamed.append(f"{key}: {str(e)[:120]}")
    assert not unnamed, unnamed
    assert checked > 40, checked
