# Two commands set fgnav up on a machine with only Python >= 3.11:
#   make demo   -> creates .venv, installs fgnav, runs the main job on a simulated flight
#   make test   -> creates .venv, installs fgnav with test and live (pymavlink) extras, runs the
#                  whole test suite
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
DEMO_OUT ?= out/demo
PYTEST_WORKERS ?= 2

.PHONY: demo test test-fast lint bench clean

$(PY):
	$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "fgnav needs Python >= 3.11, found " + sys.version.split()[0]'
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

$(VENV)/.installed: $(PY) pyproject.toml
	$(PY) -m pip install --quiet -e .
	touch $@

$(VENV)/.installed-test: $(PY) pyproject.toml
	$(PY) -m pip install --quiet -e '.[test,live]'
	touch $@ $(VENV)/.installed

demo: $(VENV)/.installed
	$(VENV)/bin/fgnav demo --out $(DEMO_OUT)

# The whole suite, slow tests included (CI runs this). pytest's exit code passes through
# unchanged: 5 ("no tests collected") fails the target like any other failure.
test: $(VENV)/.installed-test
	$(PY) -m pytest -n $(PYTEST_WORKERS) -m "slow or not slow" tests

test-fast: $(VENV)/.installed-test
	$(PY) -m pytest -n $(PYTEST_WORKERS) -m "not slow" tests

lint: $(VENV)/.installed-test
	$(VENV)/bin/ruff check fgnav factors datasets scripts tests

# Every benchmark (scripts/bench_*.py) in turn, figures printed (about 10-15 minutes on 2 cores);
# speed is measured here, never by timed tests.
bench: $(VENV)/.installed
	for s in scripts/bench_*.py; do echo "== $$s"; $(PY) $$s || exit 1; done

clean:
	rm -rf $(VENV) out .pytest_cache
