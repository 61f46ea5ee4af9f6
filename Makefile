# Two commands are the whole set-up on a fresh machine: `make run` and `make test`.
# Both create .venv on first use: torch==2.13.0 (the local CPU build) goes in first,
# then the project with a constraints file that keeps that torch.

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
HOST ?= 127.0.0.1
PORT ?= 8000
PYTEST_ARGS ?= -n 2 -m "not slow and not gpu"

.PHONY: venv kernels run test bench clean

venv: $(STAMP)

# PYTHONWARNINGS below: setuptools' "Editable installation ... be careful with folders" notice
# says nothing a user can act on, and pip would print it on every first `make run`.
$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	PYTHONWARNINGS="ignore:Editable installation" $(PY) -m pip install -q -c constraints.txt -e '.[test]'
	touch $(STAMP)

# Fused CPU kernels (C++/OpenMP, loaded through ctypes); rebuilt when a source changes.
kernels: $(STAMP)
	$(PY) -m fluidcore.kernels build

run: kernels
	$(VENV)/bin/fluidnexus serve --host $(HOST) --port $(PORT)

test: kernels
	$(PY) -m pytest $(PYTEST_ARGS)

clean:
	rm -rf fluidcore/kernels/_build .pytest_cache
