"""The checkpoint's format number (dider.models.checkpoint_format): checkpoints are written in today's format, and
every other format (a development version's before 0.2, with no number; a newer one) is refused by name at every
door, with what reads it; a fresh build passes through no compatibility code."""

from __future__ import annotations

import pytest
import torch

import dider
from dider.models.checkpoint_format import FORMAT, read
from dider.models.inference import plain_config
from dider.models.vae import RelationalVAE
from dider.training.module import RelationalVAEModule
from dider.training.runfolder import check_checkpoint
from dider.validation import ConfigError


def today(make_cfg, *overrides: str) -> RelationalVAEModule:
    return RelationalVAEModule.from_config(make_cfg(["model=dider", *overrides]).model)


def test_checkpoints_are_written_in_todays_format(make_cfg):
    checkpoint: dict = {}
    today(make_cfg).on_save_checkpoint(checkpoint)
    assert checkpoint["dider"]["format"] == FORMAT and "version" in checkpoint["dider"]


@pytest.mark.parametrize("mark, by", [(None, "a development version before 0.2.0: retrain it"),
                                      (FORMAT - 1, "a development version before 0.2.0: retrain it"),
                                      (FORMAT + 1, "a newer dider: upgrade the package")])
def test_another_format_is_refused_by_name_at_every_door(make_cfg, tmp_path, mark, by):
    """The shipped DIDER's file with its format mark removed (format 1: no number), an older number (format 2: the
    data arguments flat) or a newer one: read(), the
    ``ckpt_path=`` check, dider.load and the LightningModule's loader each refuse it naming the file and the format."""
    from dider.shipped import HERE, catalog

    ckpt = torch.load(HERE / catalog()["synth/dider"]["file"], map_location="cpu", weights_only=True)
    if mark is None:
        del ckpt["dider"]["format"]
    else:
        ckpt["dider"]["format"] = mark
    torch.save(ckpt, path := tmp_path / "other.ckpt")
    found = 1 if mark is None else mark
    why = rf"other.ckpt: written in checkpoint format {found} by {by}.*; this version reads format {FORMAT}"
    for door in (read, dider.load, RelationalVAEModule.load_from_checkpoint):
        with pytest.raises(ValueError, match=why):
            door(path)
    with pytest.raises(ConfigError, match=rf"^ckpt_path=\S*{why}"):
        check_checkpoint(str(path), {"net": {}})


def test_a_fresh_build_passes_through_no_compatibility_code(make_cfg):
    """A config written today with a format-1 loss setting does not build: nothing reads that layout."""
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


def test_one_reader_opens_every_checkpoint():
    """``torch.load`` of a checkpoint happens in one function (the caches and DNRI's data files are no checkpoints),
    and Lightning's loads (a resumed or tested run) go through it too."""
    from pathlib import Path

    import dider.data.cache
    import dider.data.readers.dnri_files
    import dider.models.checkpoint_format

    src = Path(dider.__file__).parent
    allowed = {Path(m.__file__) for m in (dider.models.checkpoint_format, dider.data.cache,
                                          dider.data.readers.dnri_files)}
    loads = {p for p in src.rglob("*.py") if "torch.load(" in p.read_text() and p not in allowed}
    assert not loads, loads
    assert dider.models.checkpoint_format.read.__code__.co_names.count("load") == 1


def test_lightnings_loads_go_through_the_reader(tmp_path):
    from dider.shipped import HERE, catalog
    from dider.training.checkpoint import AtomicCheckpointIO

    ckpt = torch.load(HERE / catalog()["synth/dider"]["file"], map_location="cpu", weights_only=True)
    assert AtomicCheckpointIO().load_checkpoint(HERE / catalog()["synth/dider"]["file"]).keys() == ckpt.keys()
    del ckpt["dider"]["format"]
    torch.save(ckpt, path := tmp_path / "old.ckpt")
    with pytest.raises(ValueError, match=r"old.ckpt: written in checkpoint format 1"):
        AtomicCheckpointIO().load_checkpoint(path)


def test_a_checkpoint_setting_the_module_does_not_take_is_refused_not_dropped(tmp_path):
    """A key of the hyper-parameters' top level that no setting reads (a hand edit, a setting of another version) is
    named, not silently left out of the model that is built."""
    from dider.shipped import HERE, catalog

    ckpt = torch.load(HERE / catalog()["synth/dider"]["file"], map_location="cpu", weights_only=True)
    ckpt["hyper_parameters"]["burn_in"] = 5  # the protocol's key where format 2 kept it
    torch.save(ckpt, path := tmp_path / "extra.ckpt")
    with pytest.raises(ConfigError, match=r"model config: burn_in: not a setting of the model's top level"):
        RelationalVAEModule.from_checkpoint(path)
