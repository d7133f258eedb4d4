"""Tensors made during a step or a metric's compute are made on the device of what they meet. A tensor built on the
CPU there is, on a GPU, a host copy (which a CUDA graph cannot hold) or a device mismatch (``torch.stack`` of a CUDA
and a CPU tensor fails): bugs a CPU run never shows. This reads the code: every ``torch.<factory>(...)`` call in the
models, the metrics and the training module names its ``device``, unless it builds a parameter, a buffer or a metric
state (moved with the module) or is listed below with its reason."""

from __future__ import annotations

import ast
from pathlib import Path

import dider

FACTORIES = {"tensor", "as_tensor", "zeros", "ones", "full", "empty", "arange", "linspace", "eye", "rand", "randn"}
MOVED_WITH_THE_MODULE = {"Parameter", "add_state", "register_buffer"}
HOST_ON_PURPOSE = {
    ("structure.py", "match_types"): "the Hungarian algorithm runs in Python on the host; its result is moved",
    ("prior.py", "fixed_log_probs"): "a constructor's buffer, registered and moved with the module",
}
PACKAGE = Path(dider.__file__).parent
FILES = [*sorted((PACKAGE / "models").glob("*.py")), *sorted((PACKAGE / "evaluation").glob("*.py")),
         PACKAGE / "graph.py", PACKAGE / "training" / "module.py", PACKAGE / "training" / "graphed.py"]


def host_tensors(path: Path, root: Path = PACKAGE) -> list[str]:
    tree = ast.parse(path.read_text())
    parent = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}

    def enclosing_function(node: ast.AST) -> str | None:
        while node in parent:
            node = parent[node]
            if isinstance(node, ast.FunctionDef):
                return node.name
        return None

    found = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in FACTORIES
                and isinstance(node.func.value, ast.Name) and node.func.value.id == "torch"):
            continue
        wrapper = parent.get(node)
        wrapped = isinstance(wrapper, ast.Call) and getattr(wrapper.func, "attr", getattr(wrapper.func, "id", None)) \
            in MOVED_WITH_THE_MODULE
        function = enclosing_function(node)
        if any(k.arg == "device" for k in node.keywords) or wrapped or function == "__init__" \
                or (path.name, function) in HOST_ON_PURPOSE:
            continue
        found.append(f"{path.relative_to(root)}:{node.lineno} torch.{node.func.attr} in {function}")
    return found


def test_step_and_metric_tensors_are_made_on_their_device():
    assert [h for f in FILES for h in host_tensors(f)] == []


def test_the_check_sees_a_host_tensor(tmp_path):
    code = tmp_path / "m.py"
    code.write_text("import torch\n\n\ndef compute(x):\n    return torch.stack([x, torch.tensor(1.0)])\n")
    assert host_tensors(code, tmp_path) == ["m.py:5 torch.tensor in compute"]
