"""What the tests share besides pytest fixtures: data files in each supported format (:mod:`helpers.fixtures`),
the explorer's clips and headless-Chromium helpers (:mod:`helpers.explore`) and reference baselines
(:mod:`helpers.baselines`). Importable as ``helpers`` because pytest puts ``tests/`` on the path
(``pythonpath`` in pyproject.toml)."""

from dider.bench.cases import NO_SPARSITY  # noqa: F401 (the overrides that leave the sparsity term out)
