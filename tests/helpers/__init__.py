"""What the tests share besides pytest fixtures: data files in each supported format (:mod:`helpers.fixtures`),
the explorer's clips and headless-Chromium helpers (:mod:`helpers.explore`) and reference baselines
(:mod:`helpers.baselines`). Importable as ``helpers`` because pytest puts ``tests/`` on the path
(``pythonpath`` in pyproject.toml)."""
