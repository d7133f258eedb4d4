# dider: `make demo` trains and evaluates on the embedded synthetic set; `make test` runs the tests.
# Both install what they need into .venv on a fresh machine.
PY      ?= python3
VENV    ?= .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
TORCH   := torch==2.13.0

.PHONY: help install demo test test-all bench tb docs lint clean

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  %-10s %s\n", $$1, $$2}'

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# the pinned CPU wheel first: an unpinned torch would pull a multi-GB CUDA build
	$(BIN)/pip install -q $(TORCH)
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)  ## create .venv with the pinned CPU torch and the package (editable)

demo: $(STAMP)  ## train + evaluate DIDER on a small synthetic set (CPU, minutes)
	$(BIN)/python -m dider.run experiment=demo

test: $(STAMP)  ## fast test suite (CPU, < 15 min)
	$(BIN)/python -m pytest -m "not slow" -q --durations=15

test-all: $(STAMP)  ## every test, including the slow end-to-end ones
	$(BIN)/python -m pytest -q

bench: $(STAMP)  ## training throughput benchmarks -> bench/results.json
	$(BIN)/python -m dider.bench --out bench/results.json

tb: $(STAMP)  ## TensorBoard over single runs and sweeps
	$(BIN)/tensorboard --logdir_spec runs:runs,multirun:multirun --port 6006

docs: $(STAMP)  ## build the documentation site into site/ (broken links fail); serve: .venv/bin/mkdocs serve
	$(BIN)/mkdocs build --strict

lint: $(STAMP)  ## ruff
	$(BIN)/ruff check src tests

clean:  ## remove caches and build outputs (keeps runs/ and multirun/)
	rm -rf build dist src/*.egg-info .pytest_cache .ruff_cache
	find . -name __pycache__ -type d -prune -exec rm -rf {} +
