"""The documentation site builds with MkDocs in strict mode (a broken link or a missing page fails), and the
API reference is generated from the docstrings."""

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytest.importorskip("mkdocs")
pytest.importorskip("mkdocstrings_handlers.python")


def build(root: Path, site: Path) -> subprocess.CompletedProcess:
    # not -q: MkDocs counts the warnings that strict mode fails on only at the WARNING log level
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(root / "mkdocs.yml"),
                           "-d", str(site)], capture_output=True, text=True, timeout=300, cwd=root)


def test_site_builds_with_the_api_reference(tmp_path):
    proc = build(ROOT, tmp_path / "site")
    assert proc.returncode == 0, proc.stderr[-3000:]
    api = (tmp_path / "site" / "api" / "index.html").read_text()
    assert "TrainedModel" in api and "forecast" in api and "edge_probabilities" in api  # from the docstrings


def test_a_broken_link_fails_the_build(tmp_path):
    shutil.copy(ROOT / "mkdocs.yml", tmp_path / "mkdocs.yml")
    shutil.copytree(ROOT / "docs", tmp_path / "docs")
    shutil.copytree(ROOT / "src", tmp_path / "src")  # the API reference reads the package's source
    page = tmp_path / "docs" / "metrics.md"
    page.write_text(page.read_text() + "\nSee [the old page](no_such_page.md).\n")
    proc = build(tmp_path, tmp_path / "site")
    assert proc.returncode != 0 and "no_such_page.md" in proc.stderr


def _expand(token: str) -> list[str]:
    """``a{1..3}b`` and ``a{x,y}b`` as a shell expands them (one brace group)."""
    m = re.search(r"\{([^{}]*)\}", token)
    if not m:
        return [token]
    body = m.group(1)
    if (rng := re.fullmatch(r"(\d+)\.\.(\d+)", body)) is not None:
        items = [str(i) for i in range(int(rng.group(1)), int(rng.group(2)) + 1)]
    else:
        items = body.split(",")
    return [token[: m.start()] + item + token[m.end():] for item in items]


def test_every_cited_record_is_committed_and_every_record_cited():
    """Every figure in the docs comes from a record in the repository: a ``docs/records/*.json`` the README, the
    docs, the journal or the CHANGELOG name must exist, and a record nothing names is a figure without a page."""
    pages = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").rglob("*.md"))]
    text = "\n".join(page.read_text() for page in pages)
    tokens = re.findall(r"docs/records/([\w{},.]+?\.json)", text)
    cited = {name for token in tokens if token.islower() for name in _expand(token)}  # NAME, seedS: placeholders
    records = {path.name for path in (ROOT / "docs" / "records").glob("*.json")}
    assert cited - records == set(), "named in the docs but not committed"
    named = {name for token in re.findall(r"[\w{},.]+\.json", text) for name in _expand(token)}
    assert records - named == set(), "committed but named nowhere"
