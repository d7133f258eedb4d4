"""The checkpoint's format number and the one step that reads an older checkpoint as today's
(dider.models.checkpoint_format): every older layout loads, with the loss and the weights it had; a fresh build
passes through no compatibility code; a newer format is refused by name."""

from __future__ import annotations

import lightning
import pytest
import torch

from dider.models.checkpoint_format import FLAT_MODULE_KEYS, FORMAT, format_of, read, upgrade
from dider.models.inference import plain_config
from dider.models.plugins import Progress
from dider.models.vae import RelationalVAE
from dider.training.module import RelationalVAEModule
from dider.training.runfolder import check_checkpoint
from dider.validation import ConfigError
from helpers.models import clip

# The loss settings of a format-1 DIDER config (at the top of the network's config), and what they mean today.
OLD_DIDER = {"nll_variance": 5e-5, "beta_edge": 1.0, "beta_duration": 1.0, "capacity_edge": 0.0,
             "capacity_duration": 0.0, "capacity_ramp": 0.5, "kl_warmup": 0.0, "sparsity_mix": 0.5,
             "no_edge_prob": 0.75, "sparsity_form": "per_edge", "segment_kl": "per_segment", "prior_fit": 1.0,
             "prior_fit_warmup": True}


def today(make_cfg, *overrides: str) -> RelationalVAEModule:
    return RelationalVAEModule.from_config(make_cfg(["model=dider", "model/net/objective=dider",
                                                     "model.net.objective.boundary_fit=null", *overrides]).model)


def format_one(module: RelationalVAEModule, flat: bool = False) -> dict:
    """The module as a format-1 checkpoint: the network's config named ``model``, its loss settings at its top
    (and, ``flat``, the module's settings inside it), the variance as ``likelihood.variance``, no format number."""
    hparams = dict(module.hparams)
    net = {k: v for k, v in hparams.pop("net").items() if k != "objective"} | OLD_DIDER
    if flat:
        net |= {k: hparams.pop(k) for k in FLAT_MODULE_KEYS}
    hparams["model"] = net
    state = {k.replace("objective.terms.nll.", "likelihood."): v for k, v in module.state_dict().items()}
    return {"state_dict": state, "hyper_parameters": hparams, "pytorch-lightning_version": lightning.__version__}


@pytest.mark.parametrize("flat", [False, True])
def test_a_format_one_checkpoint_reads_as_today(make_cfg, flat):
    """Its network's config is today's (the objective rebuilt from the loss settings), the module's settings sit at
    the top of the hyper-parameters, the weights have today's names, and the format is today's."""
    new = today(make_cfg)
    ckpt = upgrade(format_one(new, flat))
    terms = {k: v for k, v in new.hparams.net["objective"].items() if v is not None}
    assert "model" not in ckpt["hyper_parameters"] and ckpt["hyper_parameters"]["net"]["objective"] == terms
    assert {k: ckpt["hyper_parameters"][k] for k in FLAT_MODULE_KEYS} == {k: new.hparams[k] for k in FLAT_MODULE_KEYS}
    assert ckpt["state_dict"].keys() == new.state_dict().keys() and format_of(ckpt) == FORMAT


def test_the_old_loss_settings_compute_the_same_loss(make_cfg):
    """The objective rebuilt from a format-1 config's loss settings gives the loss of today's config, term by term."""
    new = today(make_cfg)
    ckpt = upgrade(format_one(new))
    a, b = new.model, RelationalVAE.from_config(ckpt["hyper_parameters"]["net"])
    b.load_state_dict({k.removeprefix("model."): v for k, v in ckpt["state_dict"].items()})
    batch = clip()
    torch.manual_seed(1)
    la = a.loss(a.infer(batch, hard=True), Progress(10, 100))
    torch.manual_seed(1)
    lb = b.loss(b.infer(batch, hard=True), Progress(10, 100))
    assert la.keys() == lb.keys() and all(torch.equal(la[k], lb[k]) for k in la)


def test_a_format_one_file_loads_through_the_lightning_module(make_cfg, tmp_path):
    """``RelationalVAEModule.load_from_checkpoint`` reads the file in today's format: today's objective, all weights."""
    new = today(make_cfg)
    torch.save(format_one(new, flat=True), path := tmp_path / "old.ckpt")
    old = RelationalVAEModule.load_from_checkpoint(path)
    assert list(old.model.objective.terms) == list(new.model.objective.terms)
    loaded = old.state_dict()
    assert loaded.keys() == new.state_dict().keys()
    assert all(torch.equal(loaded[k], v) for k, v in new.state_dict().items())


def test_a_format_one_segment_end_keeps_its_prior_and_readout(make_cfg):
    """A segment end from before its prior read the held type (no online_prior, no end_readout; the prior's MLP as
    prior.0 / prior.2) reads as the past's prior and the median end, its weights under today's names; a hold gate's
    own prior.0 keeps its name."""
    new = today(make_cfg, "model.net.duration.online_prior=past")
    old = format_one(new)
    for key in ("online_prior", "end_readout", "num_types"):
        old["hyper_parameters"]["model"]["duration"].pop(key)
    old["state_dict"] = {k.replace("duration.prior.past.", "duration.prior."): v for k, v in old["state_dict"].items()}
    ckpt = upgrade(old)
    net = RelationalVAE.from_config(ckpt["hyper_parameters"]["net"])
    assert net.duration.end_readout == "median" and not net.duration.prior.held and net.capabilities.online_retype
    net.load_state_dict({k.removeprefix("model."): v for k, v in ckpt["state_dict"].items()})
    gate = RelationalVAEModule.from_config(make_cfg(["model=dider_gate"]).model)
    keys = {k for k in gate.state_dict() if ".duration.prior.0." in k}
    assert keys and keys <= set(upgrade(format_one_state(gate))["state_dict"])


def format_one_state(module: RelationalVAEModule) -> dict:
    return {"state_dict": dict(module.state_dict()), "hyper_parameters": {"net": plain_config(module.hparams.net)}}


def test_a_resumed_run_reads_a_format_one_state(make_cfg):
    """Lightning hands a resumed or tested run's checkpoint to ``on_load_checkpoint``: the network's weights at the
    top of the state dict (the oldest layout) come under ``model.``."""
    module = RelationalVAEModule.from_config(make_cfg(["model=dnri"]).model)
    old = {"state_dict": {k.removeprefix("model."): v for k, v in module.state_dict().items()}}
    module.on_load_checkpoint(old)
    module.load_state_dict(old["state_dict"])
    assert set(old["state_dict"]) == set(module.state_dict()) and format_of(old) == FORMAT


def test_checkpoints_are_written_in_todays_format_and_a_newer_one_is_refused(make_cfg, tmp_path):
    module = today(make_cfg)
    checkpoint: dict = {}
    module.on_save_checkpoint(checkpoint)
    assert checkpoint["dider"]["format"] == FORMAT and "version" in checkpoint["dider"]
    newer = format_one(module) | {"dider": {"format": FORMAT + 1}}
    torch.save(newer, path := tmp_path / "newer.ckpt")
    with pytest.raises(ValueError, match=rf"newer.ckpt: written in checkpoint format {FORMAT + 1} by a newer dider"):
        read(path)
    with pytest.raises(ConfigError, match=rf"^ckpt_path=\S*newer.ckpt: written in checkpoint format {FORMAT + 1} "):
        check_checkpoint(str(path), {"net": {}})


def test_a_fresh_build_passes_through_no_compatibility_code(make_cfg):
    """Only a checkpoint's read upgrades: a config written today with a format-1 loss setting does not build."""
    net = plain_config(make_cfg(["model=dider"]).model.net) | {"nll_variance": 5e-5}
    with pytest.raises(Exception, match="nll_variance"):
        RelationalVAE.from_config(net)


def test_a_string_setting_that_fixes_shapes_is_compared_with_the_checkpoints(make_cfg, tmp_path):
    """``ckpt_path=`` is refused before any work when a plugin setting its class names in ``SHAPES`` differs from
    the checkpoint's, the checkpoint's value read at its constructor's default where it predates the setting (here
    the shipped DIDER as a checkpoint written before ``posterior_reads`` would hold it); the old value is one
    override away."""
    from omegaconf import OmegaConf

    from dider.shipped import HERE, catalog

    ckpt = torch.load(HERE / catalog()["synth/dider"]["file"], map_location="cpu", weights_only=True)
    del ckpt["hyper_parameters"]["net"]["encoder"]["posterior_reads"]
    path = str(tmp_path / "before_posterior_reads.ckpt")
    torch.save(ckpt, path)

    def model(*overrides: str) -> dict:
        cfg = make_cfg(["model=dider", "experiment=synth_protocol", *overrides], tiny=False)
        return OmegaConf.to_container(cfg.model, resolve=True)

    with pytest.raises(ConfigError, match=r"\(pass its settings: model\.net\.encoder\.posterior_reads=sequence\)"
                                          r":\n  - model\.net\.encoder\.posterior_reads: checkpoint 'sequence', "
                                          r"config 'transition'$"):
        check_checkpoint(path, model())
    check_checkpoint(path, model("model.net.encoder.posterior_reads=sequence"))
    with pytest.raises(ConfigError, match=r"model\.net\.duration\.online_prior: checkpoint 'held_type', config "
                                          r"'past'"):
        check_checkpoint(path, model("model.net.encoder.posterior_reads=sequence",
                                     "model.net.duration.online_prior=past"))
