"""What the tests share besides pytest fixtures: data files in each supported format (:mod:`helpers.fixtures`),
the explorer's clips and headless-Chromium helpers (:mod:`helpers.explore`) and reference baselines
(:mod:`helpers.baselines`). Importable as ``helpers`` because pytest puts ``tests/`` on the path
(``pythonpath`` in pyproject.toml)."""

# The overrides that leave the sparsity term out, the edge KL at full weight.
NO_SPARSITY = ["model.objective.sparsity=null", "model.objective.kl_edge.weight=1"]
