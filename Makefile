# Everything runs in a project-local virtual environment that `make` creates on first use.
PYTHON ?= python3.11
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test bench lint clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test,dask]'
	@touch $(STAMP)

# The package's bytecode, written before every run: an editable install compiles none, and where
# $$PYTHONDONTWRITEBYTECODE is set (as on the machines here) every process would otherwise compile
# the package's source again (0.22-0.37 s of each `diagnose`, benchmarks/results/profile.md).
COMPILE := $(PY) -m compileall -q hartrao_jax

demo: $(STAMP)
	@$(COMPILE)
	$(VENV)/bin/hartrao-jax demo --out demo-output

test: $(STAMP)
	@$(COMPILE)
	$(PY) -m pytest

bench: $(STAMP)
	$(PY) -m pip install -q -e '.[bench]'
	$(PY) benchmarks/run_all.py

lint: $(STAMP)
	$(PY) -m pip install -q -e '.[lint]'
	$(VENV)/bin/ruff check hartrao_jax tests benchmarks

clean:
	rm -rf $(VENV) demo-output .pytest_cache build dist
