"""A file dider reads is data: a checkpoint's (or a run folder's) config builds dider's own classes where their
kind goes, and classes the user trusts; any other ``_target_`` is refused, naming the file, the key and the target,
before anything is imported or called. Each payload is planted beside every ``_target_`` of a real checkpoint and as
whole nodes, and sent through every door that reads one; none may leave its marker file."""

from __future__ import annotations

import base64
import copy
import json
import pickle
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import torch

import dider
from dider.analysis.diagnose import diagnose
from dider.analysis.ship import slim
from dider.models.checkpoint_format import read
from dider.models.vae import RelationalVAE
from dider.run import predict, train
from dider.shipped import HERE, catalog
from dider.targets import Untrusted, build
from dider.training.module import RelationalVAEModule

pytestmark = pytest.mark.usefixtures("one_thread")
SHIPPED = HERE / "synth_dnri.ckpt"


class _Touch:
    """A pickle that creates ``path`` when it is loaded."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)

    def __reduce__(self) -> tuple[Any, ...]:
        return open, (self.path, "w")


def payloads(mark: Path) -> dict[str, dict[str, Any]]:
    """Nodes that, built by Hydra's ``instantiate``, each create ``mark``."""
    blob = base64.b64encode(pickle.dumps(_Touch(mark))).decode()
    return {
        "write_text": {"_target_": "pathlib.Path.write_text",
                       "_args_": [{"_target_": "pathlib.Path", "_args_": [str(mark)]}, "pwned"]},
        "pickle_as_text": {"_target_": "torch.load", "weights_only": False,
                           "f": {"_target_": "io.BytesIO", "_args_": [{"_target_": "base64.b64decode",
                                                                         "_args_": [blob]}]}},
        "os_system": {"_target_": "os.system", "_args_": [f"touch {mark}"]},
        "exec": {"_target_": "builtins.exec", "_args_": [f"open({str(mark)!r}, 'w')"]},
        "dider_writer": {"_target_": "dider.io.atomic_write_text", "path": str(mark), "text": "pwned"},
        "partial": {"_target_": "dider.io.atomic_write_text", "_partial_": True, "path": str(mark), "text": "x"},
        "nested_args": {"_target_": "dider.models.encoder.GNNLSTMEncoder",
                        "_args_": [{"_target_": "dider.io.atomic_write_text", "path": str(mark), "text": "x"}]},
    }


def targets_of(node: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[str, ...]]:
    """The key path of every node with a ``_target_``."""
    if isinstance(node, dict):
        if "_target_" in node:
            yield path
        for key, value in node.items():
            yield from targets_of(value, (*path, key))


def at(node: dict[str, Any], path: tuple[str, ...]) -> dict[str, Any]:
    for key in path:
        node = node[key]
    return node


def plantings(mark: Path) -> Iterator[tuple[str, dict[str, Any]]]:
    """(name, checkpoint) with one payload planted: beside every ``_target_`` and in place of every node."""
    clean = read(SHIPPED)
    sites = list(targets_of(clean["hyper_parameters"]))
    assert len(sites) >= 8, sites  # the network, its four plugins, the objective and its terms, the optimiser
    for form, payload in payloads(mark).items():
        for site in sites:
            beside = copy.deepcopy(clean)
            at(beside["hyper_parameters"], site)["evil"] = copy.deepcopy(payload)
            yield f"{form} beside {'.'.join(site)}", beside
            whole = copy.deepcopy(clean)
            *parent, key = site
            at(whole["hyper_parameters"], tuple(parent))[key] = copy.deepcopy(payload)
            yield f"{form} as {'.'.join(site)}", whole
        term = copy.deepcopy(clean)  # a term nobody compares or reads
        term["hyper_parameters"]["net"]["objective"]["unread"] = copy.deepcopy(payload)
        yield f"{form} as a new term", term


API_DOORS = {
    "dider.load": lambda path: dider.load(path),
    "RelationalVAE.from_checkpoint": RelationalVAE.from_checkpoint,
    "RelationalVAEModule.load_from_checkpoint": RelationalVAEModule.load_from_checkpoint,
    "ship": slim,
}


def test_no_payload_runs_through_the_api_doors(tmp_path):
    mark, count = tmp_path / "pwned", 0
    for name, ckpt in plantings(mark):
        path = tmp_path / "planted.ckpt"
        torch.save(ckpt, path)
        for door, read_it in API_DOORS.items():
            with pytest.raises(Untrusted, match=f"^{path}: hyper_parameters") as refused:
                read_it(path)
            assert "_target_" in str(refused.value) or "_partial_" in str(refused.value) \
                or "_args_" in str(refused.value) or "not plain data" in str(refused.value), (name, door)
            assert not mark.exists(), (name, door)
            count += 1
    assert count >= 7 * 16 * len(API_DOORS)


def test_a_refusal_names_the_file_the_key_and_the_target(tmp_path):
    ckpt = read(SHIPPED)
    ckpt["hyper_parameters"]["net"]["objective"]["kl_edge"]["evil"] = payloads(tmp_path / "m")["os_system"]
    torch.save(ckpt, path := tmp_path / "planted.ckpt")
    with pytest.raises(Untrusted, match=rf"^{path}: hyper_parameters\.net\.objective\.kl_edge\.evil\._target_="
                                        r"'os\.system': no class is built there"):
        dider.load(path)
    ckpt = read(SHIPPED)
    ckpt["hyper_parameters"]["net"]["encoder"]["_target_"] = "dider.io.atomic_write_text"
    torch.save(ckpt, path)
    with pytest.raises(Untrusted, match=r"hyper_parameters\.net\.encoder\._target_='dider\.io\.atomic_write_text': "
                                        r"not one of dider's encoder classes"):
        dider.load(path)


@pytest.fixture
def planted(tmp_path) -> tuple[Path, Path]:
    """A checkpoint with the pickle-as-text payload planted as an objective term nobody reads: (file, marker)."""
    mark = tmp_path / "pwned"
    ckpt = read(SHIPPED)
    ckpt["hyper_parameters"]["net"]["objective"]["unread"] = payloads(mark)["pickle_as_text"]
    torch.save(ckpt, path := tmp_path / "planted.ckpt")
    return path, mark


def test_no_payload_runs_through_eval_or_predict(make_cfg, tmp_path, planted):
    path, mark = planted
    with pytest.raises(Untrusted, match=r"hyper_parameters\.net\.objective\.unread\._target_='torch\.load'"):
        train(make_cfg([*catalog()["synth/dnri"]["evaluate"], "mode=eval", f"ckpt_path={path}"], tiny=False,
                       out=tmp_path / "eval"))
    assert not mark.exists()
    npz = tmp_path / "tracks.npz"
    from helpers.fixtures import write_trajectories

    write_trajectories(npz, num=4, steps=12, agents=3)
    with pytest.raises(Untrusted, match=r"hyper_parameters\.net\.objective\.unread"):
        predict(make_cfg(["mode=predict", f"ckpt_path={path}", "data=trajectories", f"data.source.path={npz}"],
                         out=tmp_path / "predict"))
    assert not mark.exists()


def test_no_payload_runs_through_diagnose(tmp_path, planted):
    path, mark = planted
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    path.rename(run / "checkpoints" / "last.ckpt")
    data = {"_target_": "dider.data.clips.ClipsDataModule"}
    (run / "metrics.json").write_text(json.dumps({"metrics": {}, "config": {"data": data}}))
    with pytest.raises(Untrusted, match="unread"):
        diagnose(run)
    torch.save(read(SHIPPED), run / "checkpoints" / "last.ckpt")  # a clean checkpoint, the run's data node planted
    node = payloads(mark)["write_text"]
    (run / "metrics.json").write_text(json.dumps({"metrics": {}, "config": {"data": node}}))
    with pytest.raises(Untrusted, match=r"metrics\.json: data\._target_='pathlib\.Path\.write_text'"):
        diagnose(run)
    for source, why in ((node, r"data\.source\._target_='pathlib\.Path\.write_text': not one of dider's clip "
                               r"source classes"),
                        ({"_target_": "dider.data.track_sources.TableFile"}, r"data\.source\._target_="
                         r"'dider\.data\.track_sources\.TableFile': not one of dider's clip source classes"),
                        ({"_target_": "dider.data.simulators.push.Push", "seed": node}, r"data\.source\.seed\."
                         r"_target_='pathlib\.Path\.write_text': no class is built there")):
        data = {"_target_": "dider.data.clips.ClipsDataModule", "source": source}  # the source planted
        (run / "metrics.json").write_text(json.dumps({"metrics": {}, "config": {"data": data}}))
        with pytest.raises(Untrusted, match=rf"metrics\.json: {why}"):
            diagnose(run)
    assert not mark.exists()


def test_a_users_own_plugin_loads_when_trusted(tmp_path):
    ckpt = read(SHIPPED)
    ckpt["hyper_parameters"]["net"]["encoder"]["_target_"] = "helpers.user_plugins.MyEncoder"
    torch.save(ckpt, path := tmp_path / "mine.ckpt")
    with pytest.raises(Untrusted, match=r"encoder\._target_='helpers\.user_plugins\.MyEncoder'.*trust="):
        dider.load(path)
    model = dider.load(path, trust=["helpers.user_plugins.MyEncoder"])
    assert type(model.network.encoder).__name__ == "MyEncoder"
    again = RelationalVAEModule.from_checkpoint(path, trust=["helpers.user_plugins.MyEncoder"])
    mine, theirs = again.model.state_dict(), model.network.state_dict()
    assert mine.keys() == theirs.keys() and all(torch.equal(mine[k], theirs[k]) for k in mine)


@pytest.mark.parametrize("target, why", [("helpers.user_plugins.not_a_class", "not a class"),
                                         ("pathlib.Path", r"not a encoder plugin \(missing"),
                                         ("helpers.user_plugins.NoSuch", "no such class")])
def test_trust_never_builds_a_function_or_a_class_of_another_kind(tmp_path, target, why):
    ckpt = read(SHIPPED)
    ckpt["hyper_parameters"]["net"]["encoder"]["_target_"] = target
    torch.save(ckpt, path := tmp_path / "mine.ckpt")
    with pytest.raises(Exception, match=why):
        dider.load(path, trust=[target])


def test_a_runs_own_config_builds_by_the_same_rule():
    """The user's config is the user's choice (every class it names is trusted), but a class still goes where its
    kind goes."""
    node = read(SHIPPED)["hyper_parameters"]["net"]
    assert isinstance(RelationalVAE.from_config(node), RelationalVAE)
    wrong = copy.deepcopy(node)
    wrong["encoder"]["_target_"] = "dider.models.prior.LearnedPrior"
    with pytest.raises(Untrusted, match="encoder"):
        build(wrong, "network", "model config", "model.net", trust=["dider.models.prior.LearnedPrior"])


def test_every_builtin_class_is_a_class_of_its_kind():
    from dider.targets import BUILTIN, builtin_classes, kind_problem

    for kind in (*BUILTIN, "optimizer", "scheduler"):
        classes = builtin_classes(kind)
        assert classes, kind
        assert all(kind_problem(cls, kind) is None for cls in classes.values()), kind
