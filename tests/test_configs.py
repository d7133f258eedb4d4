"""Every config option composes and instantiates."""

import re
from pathlib import Path

import dider.conf
import pytest
import torch
from hydra.utils import instantiate

from dider.models.vae import RelationalVAE

CONF = Path(dider.conf.__file__).parent


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def test_groups_exist():
    assert set(options("trainer")) >= {"default", "cpu", "gpu", "ddp", "ddp_sim"}
    assert set(options("logger")) >= {"tensorboard", "csv", "none"}
    assert set(options("model")) >= {"dnri", "nri"}


@pytest.mark.parametrize("model", options("model"))
@pytest.mark.parametrize("decoder", options("model/net/decoder"))
def test_models_instantiate(make_cfg, model, decoder):
    cfg = make_cfg([f"model={model}", f"model/net/decoder={decoder}"])
    net = RelationalVAE.from_config(cfg.model)
    assert sum(p.numel() for p in net.parameters()) > 0
    b = {"states": torch.rand(2, 10, 3, 4), "mask": torch.ones(2, 10, 3, dtype=torch.bool)}
    assert torch.isfinite(net.loss(net.infer(b, hard=False))["loss"])


@pytest.mark.parametrize("group", ["encoder", "prior", "duration", "decoder"])
def test_plugin_options_instantiate(make_cfg, group):
    assert options(f"model/net/{group}"), group
    for option in options(f"model/net/{group}"):
        cfg = make_cfg([f"model/net/{group}={option}"])
        assert isinstance(instantiate(cfg.model.net[group]), torch.nn.Module)


@pytest.mark.parametrize("trainer", options("trainer"))
def test_trainers_compose(make_cfg, trainer):
    cfg = make_cfg([f"trainer={trainer}"], tiny=False)
    assert cfg.trainer._target_ == "lightning.pytorch.Trainer"
    if trainer in ("default", "cpu"):
        instantiate(cfg.trainer, logger=False, enable_checkpointing=False)


@pytest.mark.parametrize("logger", options("logger"))
def test_loggers_instantiate(make_cfg, logger, tmp_path):
    if logger in ("mlflow", "wandb"):  # optional extras
        pytest.importorskip(logger)
    extra = {"mlflow": [f"logger.mlflow.tracking_uri=sqlite:///{tmp_path / 'mlflow.db'}",
                        f"logger.mlflow.artifact_location={tmp_path / 'artifacts'}"]}.get(logger, [])
    cfg = make_cfg([f"logger={logger}", *extra])
    for lg in (cfg.logger or {}).values():
        instantiate(lg)


def test_callbacks_and_data_instantiate(make_cfg):
    cfg = make_cfg([])
    assert all(instantiate(c) is not None for c in cfg.callbacks.values())
    for option in options("data"):
        instantiate(make_cfg([f"data={option}"]).data, _convert_="all")


@pytest.mark.parametrize("experiment", options("experiment"))
def test_experiments_compose(make_cfg, experiment):
    make_cfg([f"experiment={experiment}"], tiny=False)


def test_console_scripts_and_one_version():
    """dider-run, dider-report, dider-explore, dider-bench resolve to callables; the installed version is
    dider.__version__ (pyproject reads it from there)."""
    from importlib.metadata import entry_points, version

    import dider

    scripts = {e.name: e for e in entry_points(group="console_scripts") if e.name.startswith("dider-")}
    assert set(scripts) == {"dider-run", "dider-report", "dider-explore", "dider-bench"}
    assert all(callable(e.load()) for e in scripts.values())
    assert version("dider") == dider.__version__


def test_every_config_folder_ships_as_a_package():
    """pyproject lists each conf/ folder and each code package (else setuptools warns at every install and a
    wheel may leave its YAML or its modules out)."""
    import tomllib

    project = tomllib.loads((CONF.parent / "pyproject.toml").read_text())
    listed = set(project["tool"]["setuptools"]["packages"])
    folders = {"dider.conf" + "".join(f".{part}" for part in p.relative_to(CONF).parts)
               for p in [CONF, *CONF.rglob("*")] if p.is_dir() and list(p.glob("*.yaml"))}
    assert folders <= listed, sorted(folders - listed)
    src = CONF.parent / "src"
    code = {".".join(p.parent.relative_to(src).parts) for p in src.glob("dider/**/__init__.py")}
    assert code <= listed, f"packages missing from pyproject.toml: {sorted(code - listed)}"


@pytest.mark.parametrize("debug", options("debug"))
def test_debug_configs_compose(make_cfg, debug):
    cfg = make_cfg([f"debug={debug}"], tiny=False)
    assert cfg.logger is None and cfg.trainer.accelerator == "cpu"


@pytest.mark.slow  # every debug option end to end, about 20 s: make test-all
def test_a_debug_run_and_its_output(tmp_path):
    """`debug=fdr` runs the whole loop on one batch; with output redirected to a file, training prints one line
    per epoch and the final table once, without the libraries' tips and deprecation notes."""
    import subprocess
    import sys

    common = [sys.executable, "-m", "dider.run", "experiment=smoke", "trainer.enable_progress_bar=false"]
    proc = subprocess.run([*common, "debug=fdr", f"hydra.run.dir={tmp_path / 'fdr'}"], capture_output=True,
                          text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    log = tmp_path / "out.log"
    with log.open("w") as f:
        proc = subprocess.run([*common, "logger=none", "trainer.max_epochs=2", f"hydra.run.dir={tmp_path / 'run'}"],
                              stdout=f, stderr=subprocess.STDOUT, timeout=300, cwd=tmp_path)
    text = log.read_text()
    assert proc.returncode == 0, text[-3000:]
    assert len(re.findall(r"epoch \d/2  train/loss_epoch \S+  val/nll \S+ .*  val/ade_vs_cv/h\d\d \S+  "
                          r"\((\d+m)?\d+s, about \S+ left\)", text)) == 2
    assert text.count("test/ade_vs_cv/h01") == 1 and "Test metric" not in text
    assert "Tip" not in text and "LeafSpec" not in text and "configure_callbacks" not in text


@pytest.mark.parametrize("name", ["eval", "predict"])
def test_eval_and_predict_configs_need_a_checkpoint(name):
    """--config-name eval / predict: the app's config with the mode set; without ckpt_path it stops at once."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    from dider.training.preflight import validate_config
    from dider.validation import ConfigError

    GlobalHydra.instance().clear()
    with initialize_config_module(version_base="1.3", config_module="dider.conf"):
        cfg = compose(config_name=name, overrides=["ckpt_path=runs/mine"])
        assert cfg.mode == name and cfg.ckpt_path == "runs/mine" and cfg.model.name == "dider"
        with pytest.raises(ConfigError, match=f"mode={name} needs ckpt_path"):
            validate_config(compose(config_name=name))
    GlobalHydra.instance().clear()


def test_each_data_set_picks_the_models_protocol(make_cfg):
    """Each data set picks its forecast protocol, which the model reads (the data have none of their own);
    ``protocol.*`` (or ``protocol=NAME``) changes it."""
    expected = {"synth": (5, [1, 15, 25], "global"), "dnri_files": (5, [1, 15, 25], "global"),
                "basketball": (40, [1, 5, 9], "global"), "ind": (5, [1, 20, 40], "per_agent"),
                "ind200": (5, [1, 40, 120, 190], "per_agent"), "table": (5, [1, 5, 10], "per_agent"),
                "springs": (29, [1, 10, 20], "global"), "charged": (29, [1, 10, 20], "global"),
                "eth_ucy": (8, [1, 6, 12], "per_agent")}
    assert set(options("protocol")) == {"synth", "basketball", "ind", "ind200", "tracking", "springs", "pedestrians"}
    for data, (burn_in, horizons, mode) in expected.items():
        cfg = make_cfg([f"data={data}"])
        for node in (cfg.protocol, cfg.model.protocol):
            assert (node.burn_in, list(node.horizons), node.burn_in_mode) == (burn_in, horizons, mode), data
        assert not {"burn_in", "horizons", "burn_in_mode"} & set(cfg.data), data
    cfg = make_cfg(["data=table", "protocol.burn_in=3", "protocol.horizons=[1,2]", "protocol.burn_in_mode=global"])
    p = cfg.model.protocol
    assert (p.burn_in, list(p.horizons), p.burn_in_mode) == (3, [1, 2], "global")
    cfg = make_cfg(["data=synth", "protocol=ind"])
    assert (list(cfg.model.protocol.horizons), cfg.model.protocol.burn_in_mode) == ([1, 20, 40], "per_agent")


def test_a_plugins_defaults_come_from_its_signature(make_cfg, tmp_path):
    """Each plugin option starts from its class's schema (dider.training.schemas): the settings its YAML leaves
    out take the constructor's defaults (composed under model=dnri, whose file sets no plugin setting), and a key
    the class does not take is refused at composition, also where an experiment file sets it (without the schema
    such a file composed and the run failed later)."""
    import inspect

    from hydra.errors import ConfigCompositionException

    from dider.training.schemas import PLUGINS

    for group in ("encoder", "prior", "duration", "decoder"):
        for option in options(f"model/net/{group}"):
            node = make_cfg(["model=dnri", f"model/net/{group}={option}"], tiny=False).model.net[group]
            cls = next(c for c in PLUGINS if f"{c.__module__}.{c.__qualname__}" == node._target_)
            folder = CONF / "model" / "net" / group
            text = (folder / f"{option}.yaml").read_text()
            text += "".join((folder / f"{w}.yaml").read_text() for w in text.split()
                            if (folder / f"{w}.yaml").is_file())
            yaml_keys = set(text.split())  # the option's own settings and those of the option it extends
            for name, p in inspect.signature(cls.__init__).parameters.items():
                if name != "self" and f"{name}:" not in yaml_keys and p.default is not p.empty:
                    assert node[name] == (list(p.default) if isinstance(p.default, tuple) else p.default), name
    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "typo.yaml").write_text("# @package _global_\nmodel:\n  net:\n    encoder:\n"
                                                       "      hiden: 8\n")
    with pytest.raises(ConfigCompositionException, match=r"Key 'hiden' not in 'GNNLSTMEncoderSchema'"):
        make_cfg([f"hydra.searchpath=[file://{tmp_path}]", "experiment=typo"], tiny=False)


def test_every_node_a_class_builds_holds_its_arguments(make_cfg, tmp_path):
    """The model's top (the LightningModule, with the network's name and num_edges), the network, its plugins,
    the objective's terms, the data modules and their sources start from their schemas: each node holds exactly its
    class's arguments, so every setting shows in the config, and an experiment file's typo at each level is
    refused."""
    import dataclasses

    from hydra.errors import ConfigCompositionException
    from omegaconf import DictConfig

    from dider.training.schemas import PLUGINS, TERMS, data_classes, module_schema, schema

    classes = {f"{c.__module__}.{c.__qualname__}": c for c in (*PLUGINS, *TERMS, *data_classes(), RelationalVAE)}

    def check(node, fields: set[str], where: str) -> None:
        assert set(node) == fields, where

    for model in options("model"):
        cfg = make_cfg([f"model={model}"], tiny=False)
        check(cfg.model, {f.name for f in dataclasses.fields(module_schema())}, model)
        nodes = [cfg.model.net, *[cfg.model.net[k] for k in ("encoder", "prior", "duration", "decoder")],
                 *[t for t in cfg.model.net.objective.values() if isinstance(t, DictConfig)]]
        for node in nodes:
            if (cls := classes.get(node._target_)) is not None:  # constant_velocity's decoder is a stand-in
                check(node, {f.name for f in dataclasses.fields(schema(cls))}, f"{model}: {node._target_}")
    for data in options("data"):
        node = make_cfg([f"data={data}"], tiny=False).data
        check(node, {f.name for f in dataclasses.fields(schema(classes[node._target_]))}, data)
        check(node.source, {f.name for f in dataclasses.fields(schema(classes[node.source._target_]))}, data)
    (tmp_path / "experiment").mkdir()
    typos = {"model": "model:\n  eval_sed: 1\n", "net": "model:\n  net:\n    gumbel_ta: 1\n",
             "term": "model:\n  net:\n    objective:\n      kl_edge:\n        wieght: 1\n",
             "data": "data:\n  seq_le: 5\n", "source": "data:\n  source:\n    num_step: 5\n"}
    for level, text in typos.items():
        (tmp_path / "experiment" / f"{level}.yaml").write_text(f"# @package _global_\n{text}")
        with pytest.raises(ConfigCompositionException, match=r"Key '\w+' not in '\w+Schema'"):
            make_cfg([f"hydra.searchpath=[file://{tmp_path}]", f"experiment={level}"], tiny=False)


@pytest.mark.parametrize("node, typo, schema", [("protocol", "burnin", "ForecastProtocol"), ("predict", "forecast_step",
                                                                                   "PredictSettings"),
                                                ("eval", "nmae", "EvalSettings")])
def test_the_apps_own_nodes_refuse_an_unknown_key(make_cfg, tmp_path, node, typo, schema):
    """protocol, predict and eval hold exactly their settings (dider.settings): an experiment file's typo is refused at
    composition, and one added on the command line (+node.key=...) by the preflight, naming the key."""
    from hydra.errors import ConfigCompositionException

    from dider.run import ConfigError, validate_config

    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "typo.yaml").write_text(f"# @package _global_\n{node}:\n  {typo}: 3\n")
    with pytest.raises(ConfigCompositionException, match=rf"Key '{typo}' not in '{schema}'"):
        make_cfg([f"hydra.searchpath=[file://{tmp_path}]", "experiment=typo"], tiny=False)
    with pytest.raises(ConfigError, match=rf"{node}.{typo}: no such setting \(expected one of \["):
        validate_config(make_cfg([f"+{node}.{typo}=3"]))
