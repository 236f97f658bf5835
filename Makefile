# Every target creates or refreshes the local virtual environment by itself.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test bench bench-models lint clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,dev]'
	@touch $(STAMP)

demo: $(STAMP)
	$(PY) -m motionflows.demo

# one pytest-xdist worker per core (at most 4), each taking whole files (module fixtures run once)
test: $(STAMP)
	$(PY) -m pytest -q -n auto --maxprocesses=4 --dist loadfile

# the speed benchmarks (issue 16's figures); the quality scripts in benchmarks/ score run
# directories you name (see each one's --help), so they are not run here
bench: $(STAMP)
	$(PY) benchmarks/moglow_speed.py
	$(PY) benchmarks/glow_fixed_speed.py

bench-models: $(STAMP)
	$(VENV)/bin/motionflows bench --data synthetic --budget quick --out runs/bench

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests experiments benchmarks
	$(VENV)/bin/ruff format --check src tests experiments benchmarks

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info src/*.egg-info
