"""The network is a plain nn.Module: built from the config, loaded from a checkpoint and rolled out with no
Trainer; the Lightning shell rebuilds itself from its checkpoint alone."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from dider.models.plugins import DurationCapabilities
from dider.run import train
from dider.training.module import RelationalVAEModule

pytestmark = pytest.mark.usefixtures("one_thread")

OVERRIDES = ["model=dider", "model.net.encoder.hidden=32", "model.net.encoder.rnn_hidden=16",
             "model.net.encoder.head_hidden=16", "model.net.decoder.hidden=32"]

# What a notebook does: build the network its checkpoint holds (config and weights, any format), forecast a
# tensor (composing the app's config would import Lightning: it describes the data and Lightning modules too).
NOTEBOOK = """
import json, sys
import torch
from dider.models.vae import RelationalVAE

model = RelationalVAE.from_checkpoint(sys.argv[1]).eval()
torch.manual_seed(0)
x = torch.rand(2, 12, 3, 4) * 2 - 1
pred = model(x, torch.ones(2, 30, 3, dtype=torch.bool), burn_in=10, num_pred=20)
print(json.dumps({"shape": list(pred.shape), "sum": pred.double().sum().item(),
                  "lightning_loaded": any(m == "lightning" or m.startswith("lightning.") for m in sys.modules)}))
"""


def test_checkpoint_weights_roll_out_without_a_trainer(make_cfg, tmp_path):
    train(make_cfg([*OVERRIDES, "logger=none", "callbacks=none", "+callbacks.ckpt._target_="
                    "lightning.pytorch.callbacks.ModelCheckpoint", f"+callbacks.ckpt.dirpath={tmp_path}/ck",
                    "+callbacks.ckpt.save_last=true"], out=tmp_path / "run"))
    ckpt = tmp_path / "ck" / "last.ckpt"
    assert ckpt.is_file()
    # One thread there as here (the fixture): a matmul split over two threads sums in another order, and the
    # 20-step roll-out carries that rounding past the tolerance below.
    done = subprocess.run([sys.executable, "-c", NOTEBOOK, str(ckpt)], capture_output=True,
                          text=True, timeout=300, cwd=tmp_path, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["shape"] == [2, 20, 3, 4]
    assert not out["lightning_loaded"]  # the network needs nothing of Lightning

    # The Lightning shell rebuilds from the checkpoint alone (configs in its hyper-parameters) and holds
    # the same weights: the same forecast, number for number.
    module = RelationalVAEModule.load_from_checkpoint(ckpt, map_location="cpu").eval()
    torch.manual_seed(0)
    x = torch.rand(2, 12, 3, 4) * 2 - 1
    pred = module(x, torch.ones(2, 30, 3, dtype=torch.bool), burn_in=10, num_pred=20)
    assert pred.double().sum().item() == pytest.approx(out["sum"], rel=1e-6, abs=1e-6)
    assert module.hparams.net["num_edges"] == 2 and module.protocol.burn_in == module.hparams.protocol["burn_in"] == 5


def test_model_config_keys_are_split(make_cfg):
    module = RelationalVAEModule.from_config(make_cfg(["model=dnri", "model.eval_seed=7"]).model)
    assert module.hparams.eval_seed == 7 and "eval_seed" not in module.hparams.net
    assert "optimizer" not in module.hparams.net and module.hparams.optimizer["lr"] == pytest.approx(5e-4)
    assert Path(module.model.__class__.__module__.replace(".", "/")).name == "vae"


def test_a_plugin_lacking_its_interface_is_named(make_cfg):
    from hydra.utils import instantiate

    from dider.models.vae import RelationalVAE

    cfg = make_cfg(["model=dnri"]).model.net
    parts = {k: instantiate(cfg[k]) for k in ("encoder", "prior", "duration", "objective")}
    with pytest.raises(TypeError, match=r"model.net.decoder: Linear is not a Decoder plugin \(missing \['init_state', "
                                        r"'stateless', 'step'\]"):
        RelationalVAE(**parts, decoder=torch.nn.Linear(2, 2))


@pytest.mark.parametrize("model, expected", [
    ("dnri", DurationCapabilities()),
    ("dider_paper", DurationCapabilities(observed=4, cut_kl=True, tau=True)),
    ("dider_gate", DurationCapabilities(boundary=True, cut_kl=True)),
    ("dider", DurationCapabilities(boundary=True, observed=4, cut_kl=True, online_retype=True, held_type=True)),
])
def test_optional_plugin_members_are_read_once_at_build(make_cfg, model, expected):
    """The duration's optional members (boundary, the burn-in's span, cut scoring, an annealed temperature,
    online re-typing, a prior that reads the held type) are declared Protocols read when the network is built
    (burn-in 5: a span of 4)."""
    from dider.models.vae import RelationalVAE

    net = RelationalVAE.from_config(make_cfg([f"model={model}"]).model)
    assert net.capabilities == expected
    assert not net.fits_kinematics
    assert RelationalVAE.from_config(make_cfg(["model.net.decoder.kinematic=true"]).model).fits_kinematics


def test_every_declared_setting_is_a_constructor_argument():
    """A class checks ``locals()`` against its ``SETTINGS``: a rule whose name no argument has would never run
    (and the preflight would pass a value the constructor refuses)."""
    import inspect

    from dider.models import decoders, durations, encoder, gate, hazard, likelihood, objective, prior, segment_end, vae

    modules = (decoders, durations, encoder, gate, hazard, likelihood, objective, prior, segment_end, vae)
    classes = {obj for module in modules
               for obj in vars(module).values() if isinstance(obj, type) and "SETTINGS" in vars(obj)}
    assert len(classes) >= 14, sorted(c.__name__ for c in classes)
    for cls in classes:
        params = set(inspect.signature(cls.__init__).parameters)
        assert set(cls.SETTINGS) <= params, (cls.__name__, set(cls.SETTINGS) - params)
