# The README's commands. `make run` and `make test` create .venv from requirements.txt when it is missing or older.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python

.PHONY: run test lint bench-vq clean-venv

$(VENV)/installed: requirements.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements.txt
	touch $@

# The main job on its built-in default: the vq demo until the maze study lands.
run: $(VENV)/installed
	$(PY) vq.py

# The whole test suite: lint, format check, unit tests and smoke runs.
test: lint
	$(PY) -m pytest -n auto

lint: $(VENV)/installed
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

bench-vq: $(VENV)/installed
	$(PY) benchmark/bench_vq.py

clean-venv:
	rm -rf $(VENV)
