"""The package's rooms and which way imports run between them (docs/architecture.md draws the same layers)."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "dider"
# modules at the package root every room may use
CORE = {"graph", "io", "perf", "protocol", "settings", "targets", "validation"}
# A room may import its own modules and any room of a lower layer; data and models know nothing of each other.
LAYERS = {"core": 0, "shipped": 0, "data": 1, "models": 1, "evaluation": 2,
          "training": 3, "outputs": 3, "trained": 4, "run": 5,
          "analysis": 6, "bench": 7}


def room(module: str) -> str:
    """dider.training.module -> training; dider.graph -> core; dider (the package's own __init__) -> core."""
    parts = module.split(".")
    if len(parts) == 1 or parts[1] in CORE:
        return "core"
    return parts[1]


def modules() -> list[tuple[str, Path]]:
    out = []
    for path in sorted(SRC.rglob("*.py")):
        name = ".".join(("dider", *path.relative_to(SRC).with_suffix("").parts)).removesuffix(".__init__")
        out.append((name, path))
    return out


def is_module(name: str) -> bool:
    path = SRC.joinpath(*name.split(".")[1:])
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def imported(path: Path) -> set[str]:
    """The dider modules a file imports: ``from dider.x import y`` counts dider.x.y where y is a module."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "dider":
            names.add(node.module)
            names |= {f"{node.module}.{a.name}" for a in node.names if is_module(f"{node.module}.{a.name}")}
        elif isinstance(node, ast.Import):
            names |= {a.name for a in node.names if a.name.split(".")[0] == "dider"}
    return names


def test_every_module_sits_in_a_known_room() -> None:
    assert {room(name) for name, _ in modules()} == set(LAYERS)


# The imports up the layers: ``dider.load`` and ``dider.pretrained`` resolve the Python API lazily, at first use.
ALLOWED = {("dider", "dider.trained"), ("dider", "dider.shipped")}


def test_imports_run_down_the_layers() -> None:
    wrong = {name: sorted(m for m in imported(path) if room(m) != room(name) and (name, m) not in ALLOWED
                          and LAYERS[room(m)] >= LAYERS[room(name)])
             for name, path in modules()}
    wrong = {name: bad for name, bad in wrong.items() if bad}
    assert not wrong, f"imports must run from higher layers to lower ({LAYERS}): {wrong}"


def test_no_module_over_400_lines() -> None:
    long = {name: n for name, path in modules() if (n := len(path.read_text().splitlines())) > 400}
    assert not long, f"split these modules by what they hold: {long}"


def runtime_imports(path: Path) -> set[str]:
    """The dider modules a file imports when it is imported: its top-level imports (not those inside a function or
    under ``if TYPE_CHECKING``)."""
    names = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "dider":
            names |= {node.module} | {f"{node.module}.{a.name}" for a in node.names
                                      if is_module(f"{node.module}.{a.name}")}
        elif isinstance(node, ast.Import):
            names |= {a.name for a in node.names if a.name.split(".")[0] == "dider"}
    return names


def test_no_import_circles() -> None:
    """No module imports, through others, a module that imports it (a circle makes import order matter)."""
    graph = {name: runtime_imports(path) - {name} for name, path in modules()}
    circles = []
    for start in graph:  # a depth-first walk from each module back to itself
        stack, seen = [(start, (start,))], set()
        while stack:
            node, trail = stack.pop()
            for nxt in graph.get(node, ()):
                if nxt == start:
                    circles.append(" -> ".join((*trail, start)))
                elif nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, (*trail, nxt)))
    assert not circles, circles


def test_the_lightning_module_stays_thin() -> None:
    """The LightningModule is handed its parts and scores nothing itself (the passes beside it do): at most 250
    lines, no method over 40, and the model config's top-level keys are its constructor's settings."""
    import inspect

    from dider.training.building import SETTINGS
    from dider.training.module import RelationalVAEModule

    path = SRC / "training" / "module.py"
    assert len(path.read_text().splitlines()) <= 250
    long = {n.name: n.end_lineno - n.lineno + 1 for n in ast.walk(ast.parse(path.read_text()))
            if isinstance(n, ast.FunctionDef) and n.end_lineno - n.lineno + 1 > 40}
    assert not long, long
    params = inspect.signature(RelationalVAEModule.__init__).parameters.values()
    assert [p.name for p in params if p.kind is p.POSITIONAL_OR_KEYWORD][1:] == list(SETTINGS)


def test_no_data_module_or_settings_node_takes_more_than_twelve_settings() -> None:
    """A data module's settings go in nested nodes (source, windows, loader); no node passes 12 either, and every
    data module says what it reads in a ``source`` node."""
    import dataclasses
    import inspect

    from dider.data.levelx.source import LevelXColumns, LevelXFiles, LevelXSource
    from dider.data.loader import Loader
    from dider.data.windowing import Windows
    from dider.targets import builtin_classes

    data = builtin_classes("data").values()
    counts = {cls.__name__: len(inspect.signature(cls.__init__).parameters) - 1 for cls in data}  # less self
    sources = [*builtin_classes("clip source").values(), *builtin_classes("track source").values()]
    nodes = (*sources, LevelXSource, LevelXFiles, LevelXColumns, Windows, Loader)
    counts |= {cls.__name__: len(dataclasses.fields(cls)) for cls in nodes}
    over = {name: n for name, n in counts.items() if n > 12}
    assert not over, f"too many settings in one place: {over}"
    assert all("source" in inspect.signature(cls.__init__).parameters for cls in data)
