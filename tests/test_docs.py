"""The documentation site builds with MkDocs in strict mode (a broken link or a missing page fails), and the
API reference is generated from the docstrings."""

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
