"""The journal's scripts (``docs/journal/*.py``) run at HEAD: each on a tiny case, in a fresh process, writing what it
promises into tmp_path (never into docs/records/); and none reads a private name of dider's (``module._infer``,
``dm._dataloader``, patching ``SegmentEnd._every_start``) or a module of the tests (``helpers.fixtures``), so that
they keep working as the package changes under them."""

from __future__ import annotations

import ast
import importlib.util
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
JOURNAL = ROOT / "docs" / "journal"
TESTS = Path(__file__).resolve().parent

# The scripts this file runs: a script added to docs/journal/ needs a test here (test_every_script_is_run_here).
RUN_HERE = {"loop_logging.py", "soccer_edges.py", "soccer_one_step.py", "springs_dynamic_edges.py",
            "springs_gradient.py", "windows_check.py"}

# One thread a process (tiny networks; a 2-core machine shared with other work); fp32 as every test run here.
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "DIDER_DEFAULT_PRECISION": "32-true", "HYDRA_FULL_ERROR": "1"}
TINY_NET = ["model.net.encoder.hidden=8", "model.net.encoder.rnn_hidden=8", "model.net.encoder.head_hidden=8",
            "model.net.decoder.hidden=8"]
QUIET = ["trainer.max_epochs=1", "protocol.samples=0", "logger=none", "callbacks.timelines.num_clips=0",
         "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false"]
SOCCER = ["data.source.options={limit:1200}"]  # the SkillCorner sample's first 1200 frames: 17 / 2 / 2 windows


def run(args: list[str], cwd: Path, timeout: int = 300) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, *args], cwd=cwd, env=ENV, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, (f"{' '.join(args)} exited {proc.returncode}:\n{proc.stdout[-2000:]}\n"
                                  f"{proc.stderr[-3000:]}")
    return proc


def script(name: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    return run([str(JOURNAL / name), *args], cwd=cwd)


def train(folder: Path, cache: Path, *overrides: str) -> Path:
    """A tiny ``python -m dider.run`` job -> its run folder."""
    run(["-m", "dider.run", *overrides, *TINY_NET, *QUIET, f"hydra.run.dir={folder}", f"data.cache_dir={cache}"],
        cwd=folder.parent)
    assert (folder / "checkpoints" / "last.ckpt").exists()
    return folder


def read(path: Path) -> dict:
    assert path.exists(), f"{path.name} not written"
    return json.loads(path.read_text())


def finite(x: float) -> bool:
    return isinstance(x, float) and math.isfinite(x)


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("journal_cache")


@pytest.fixture(scope="module")
def springs_run(tmp_path_factory: pytest.TempPathFactory, cache: Path) -> Path:
    """DNRI on experiment=springs_dynamic's data (the switching springs), one epoch of 16 clips."""
    return train(tmp_path_factory.mktemp("springs") / "run", cache, "experiment=springs_dynamic", "hydra.mode=RUN",
                 "model=dnri", "data.num_train=16", "data.num_val=8", "data.num_test=8", "data.loader.batch_size=8",
                 "data.loader.eval_batch_size=8")


@pytest.fixture(scope="module")
def soccer_run(tmp_path_factory: pytest.TempPathFactory, cache: Path) -> Path:
    """experiment=soccer (DNRI) on the first frames of kloppy's SkillCorner sample, one epoch."""
    pytest.importorskip("kloppy")
    return train(tmp_path_factory.mktemp("soccer") / "run", cache, "experiment=soccer", *SOCCER,
                 "data.loader.batch_size=4", "data.loader.eval_batch_size=4")


def test_every_script_is_run_here():
    assert {p.name for p in JOURNAL.glob("*.py")} == RUN_HERE


def test_windows_check_hashes_the_cases_and_compares(tmp_path):
    only = ["synth", "trajectories", "eth_ucy", "nri_files", "basketball_dnri"]
    proc = script("windows_check.py", "--out", str(tmp_path / "w.json"), "--only", *only,
                  "--compare", str(JOURNAL / "windows_baseline.json"), cwd=tmp_path)
    found = read(tmp_path / "w.json")
    assert set(found) == set(only)
    for name, case in found.items():
        assert "error" not in case, (name, case)
        assert {"normalizer", "frame_step", "source_names", "train", "val", "test"} <= set(case), name
    assert "differ:" in proc.stdout  # which cases differ from the baseline depends on the CPU: not asserted


def test_windows_check_cases_are_the_baselines(tmp_path):
    """Every case of the script is in windows_baseline.json and every baseline case is a case (compared by name)."""
    spec = importlib.util.spec_from_file_location("windows_check", JOURNAL / "windows_check.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    names = set(module.cases({k: str(tmp_path / k) for k in ("ind", "zhan", "dnri_bball", "traj.npz", "table.csv",
                                                               "eth", "dnri_files", "nri")}))
    assert names == set(json.loads((JOURNAL / "windows_baseline.json").read_text()))


def test_springs_gradient(tmp_path, cache):
    script("springs_gradient.py", "--out", str(tmp_path / "g.json"), "--cache", str(cache), "--clips", "16",
           "--batch", "8", "--steps", "2", "--every", "1", cwd=tmp_path)
    record = read(tmp_path / "g.json")
    assert record["command"].startswith("python ") and set(record["runs"]) == {"skip_first=False", "skip_first=True"}
    for rows in record["runs"].values():
        assert [r["step"] for r in rows] == [0, 1, 2]
        assert all(finite(r["loss"]) and 0.0 <= r["gradient_auroc"] <= 1.0 for r in rows)


def test_springs_dynamic_edges(tmp_path, cache, springs_run):
    """A DNRI run of the experiment's data, and the shipped synthetic DIDER (its GNN reads any number of agents):
    DIDER's held segments and the decoder's evidence without training a DIDER here."""
    ckpt = springs_run / "checkpoints" / "last.ckpt"
    script("springs_dynamic_edges.py", "--out", str(tmp_path / "e.json"), "--clips", "8", "--cache", str(cache),
           f"dnri={ckpt}", "dider=synth/dider", cwd=tmp_path)
    record = read(tmp_path / "e.json")
    assert record["command"].endswith(f"--clips 8 dnri={ckpt} dider=synth/dider")
    assert set(record["models"]["dnri"]) == {"per_step", "held", "prior"}  # DNRI's objective reads no evidence
    assert set(record["models"]["dider"]) == {"per_step", "held", "prior", "evidence"}
    for model in record["models"].values():
        for name, scores in model.items():
            assert set(scores) == {"auroc", "mean_on_spring", "mean_no_spring"} | ({"accuracy"} if name != "evidence"
                                                                                   else set())
            assert 0.0 <= scores["auroc"] <= 1.0


def test_soccer_edges(tmp_path, soccer_run):
    script("soccer_edges.py", str(soccer_run), "--out", str(tmp_path / "s.json"), "--override", *SOCCER,
           cwd=tmp_path)
    record = read(tmp_path / "s.json")
    assert "--split val --override" in record["command"]
    modes = record["runs"][str(soccer_run)]
    assert set(modes) == {"sample", "argmax", "none", "cv"}
    for mode in modes.values():
        assert set(mode) == {"h01", "h10", "h20"}
        assert all(finite(h["ade_m"]) and h["ade_m"] > 0 and finite(h["vs_cv"]) for h in mode.values())
    assert all(h["vs_cv"] == 1.0 for h in modes["cv"].values())


def test_soccer_one_step(tmp_path, soccer_run):
    proc = script("soccer_one_step.py", str(soccer_run), *SOCCER, "--out", str(tmp_path / "o.json"), cwd=tmp_path)
    assert "train: one-step position error model" in proc.stdout and "test: one-step" in proc.stdout
    record = read(tmp_path / "o.json")
    assert set(record) == {"command", "what", "train", "test"}  # as docs/records/soccer_one_step_dnri_seed1.json
    for split in ("train", "test"):
        assert set(record[split]) == {"model_m", "constant_velocity_m", "ratio"}
        assert record[split]["constant_velocity_m"] > 0 and finite(record[split]["ratio"])


def test_loop_logging(tmp_path):
    proc = script("loop_logging.py", "dnri", "data.num_train=32", cwd=tmp_path)  # 2 steps at batch 16
    line = json.loads(proc.stdout.strip().splitlines()[-1])
    assert set(line) == {"model", "steps", "step_ms", "log_dict_ms_per_step", "log_dict_calls"}
    assert line["model"] == "dnri" and line["steps"] == 2 and line["log_dict_calls"] >= 1


# --- what the scripts may read --------------------------------------------------------------------------------------

def modules_of_the_tests() -> set[str]:
    """The names a module of the tests imports as: tests/*.py and the packages under tests/."""
    return {p.stem for p in TESTS.glob("*.py")} | {p.name for p in TESTS.iterdir()
                                                   if p.is_dir() and (p / "__init__.py").exists()} | {"tests"}



def private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def problems(source: str, local: set[str] = frozenset()) -> list[str]:
    """What a script reads that it must not: a private name of dider's (imported, or read, set or patched as an
    attribute of anything but ``self`` / ``cls`` or a module of another package, e.g. ``torch._foreach_zero_``; also
    through getattr / setattr / hasattr) and a module of the tests (imported, or put on sys.path). ``local``: the
    sibling modules in the script's folder, which it may import."""
    tree, found = ast.parse(source), []
    tests = modules_of_the_tests() - set(local)
    other: set[str] = set()  # names bound to a module of another package than dider

    def line(node: ast.AST, what: str) -> None:
        found.append(f"line {node.lineno}: {what}")

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                top = alias.name.split(".")[0]
                if top == "dider" and any(private(part) for part in alias.name.split(".")):
                    line(node, f"import {alias.name}")
                if top in tests:
                    line(node, f"import {alias.name} (a module of the tests)")
                if top not in ("dider", *local):
                    other.add(alias.asname or top)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            top = node.module.split(".")[0]
            if top == "dider":
                parts = node.module.split(".")
                if any(private(p) for p in parts) or any(private(a.name) for a in node.names):
                    line(node, f"from {node.module} import {', '.join(a.name for a in node.names)}")
            elif top in tests:
                line(node, f"from {node.module} import ... (a module of the tests)")
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and private(node.attr):
            receiver = node.value
            if not (isinstance(receiver, ast.Name) and (receiver.id in ("self", "cls") or receiver.id in other)):
                line(node, f"{ast.unparse(node)} (a private name)")
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            if node.func.id in ("getattr", "setattr", "hasattr", "delattr") and len(node.args) >= 2:
                key = node.args[1]
                if isinstance(key, ast.Constant) and isinstance(key.value, str) and private(key.value):
                    line(node, f"{node.func.id}(..., {key.value!r}) (a private name)")
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            if node.value in ("tests", "helpers"):  # a path to the tests, e.g. Path(...) / "tests" on sys.path
                line(node, f"{node.value!r} (a path into the tests)")
    return found


@pytest.mark.parametrize("path", sorted(JOURNAL.rglob("*.py")), ids=lambda p: str(p.relative_to(JOURNAL)))
def test_no_script_reads_a_private_name_or_a_test_module(path):
    local = {p.stem for p in path.parent.glob("*.py")}
    found = [p.split(": ", 1)[1] for p in problems(path.read_text(), local)]
    assert not found, found


@pytest.mark.parametrize("source", [
    "import dider\nmodule = dider.load('x')\nmodule._infer(1)",
    "dm = make()\nfor b in dm._dataloader('train', train=False): pass",
    "import dider.models.segment_end as segment_end\nsegment_end.SegmentEnd._every_start = f",
    "from dider.models.segment_end import _cut",
    "import dider._private",
    "x = getattr(module, '_graphed', None)",
    "import sys\nsys.path.insert(0, str(Path(__file__).parents[2] / 'tests'))",
    "from helpers.fixtures import write_zhan",
    "from test_readers import write_scenes",
    "import conftest",
])
def test_the_scan_finds_each_kind(source):
    assert problems(source), source


def test_the_scan_lets_public_names_through():
    source = ("import torch\nimport numpy as np\nfrom protocol_clips import clips\nimport dider\n"
              "torch._foreach_zero_([])\nclass A:\n    def _now(self):\n        return self._t\n"
              "dm.val_dataloader()\nx.__getitems__([0])\nlen(x.__dict__)\n")
    assert problems(source, local={"protocol_clips"}) == []
