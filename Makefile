# The README's commands. `make run` and `make test` create .venv from requirements.txt when it is missing or older.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python

.PHONY: run demo-vq test test-all lint bench-vq study-goal-dqn study-mnist study-hrac-keychest study-ris bench-ris study-amigo bench-amigo study-hrac bench-hrac study-ris-sawyer bench-ris-sawyer clean-venv

$(VENV)/installed: requirements.txt requirements-nodeps.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -r requirements.txt
	$(PY) -m pip install --quiet --disable-pip-version-check --no-deps -r requirements-nodeps.txt
	touch $@

# The main job on its built-in default: goal-DQN vs DGRL on SpiralWorld with novel goals (a few minutes on a CPU).
# Every study runs through benchmark/launch.py (`$(PY) benchmark/launch.py --list-presets`); its results go to sweeps/.
run: $(VENV)/installed
	$(PY) benchmark/launch.py --preset quick

demo-vq: $(VENV)/installed
	$(PY) vq.py

# The quick tier (a few minutes on 2 cores): lint, format check, the maths and environment tests, each script's smoke
# run in both modes, one resume and one bad-input check per script. test-all (what CI runs) adds the tests that
# tests/conftest.py marks `full`: compiled-equals-eager, kill and exact-resume tests, the launcher's sweeps and Slurm.
test: lint
	$(PY) -m pytest -n auto -m "not full"

test-all: lint
	$(PY) -m pytest -n auto

lint: $(VENV)/installed
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

bench-vq: $(VENV)/installed
	$(PY) benchmark/speed/bench_vq.py

study-goal-dqn: $(VENV)/installed
	$(PY) benchmark/launch.py --preset goal-dqn

study-mnist: $(VENV)/installed
	$(PY) benchmark/launch.py --preset mnist

study-hrac-keychest: $(VENV)/installed
	$(PY) benchmark/launch.py --preset keychest

# The CPU preset of docs/dgrl_ris.md: RIS and RIS+DGRL (G = 16) on PointMaze_UMaze-v3, 3 seeds, 30,000 steps.
study-ris: $(VENV)/installed
	$(PY) benchmark/launch.py --preset ris-pointmaze

bench-ris: $(VENV)/installed
	$(PY) benchmark/speed/bench_ris.py

# The scaled-down AMIGo study of docs/dgrl_amigo.md (about 70 min on 2 cores).
study-amigo: $(VENV)/installed
	$(PY) benchmark/launch.py --preset amigo-doorkey
	$(PY) benchmark/launch.py --preset amigo-s3r1
	$(PY) benchmark/launch.py --preset amigo-s3r1-3m
	$(PY) benchmark/launch.py --preset amigo-nochannel

bench-amigo: $(VENV)/installed
	$(PY) benchmark/speed/bench_amigo.py

# The short CPU run of docs/dgrl_hrac.md: HRAC and HRAC+DGRL (G = 16) on AntMaze, 300k steps (HRAC 84 min on a core;
# DGRL about 1.7x that).
study-hrac: $(VENV)/installed
	$(PY) benchmark/launch.py --preset hrac-antmaze-cpu

# The CPU study of docs/dgrl_ris_sawyer.md: RIS and RIS+DGRL (G = 16) from pixels on push-and-reach, 2 seeds, 30,000 steps
# (about 70 min on 2 cores).
study-ris-sawyer: $(VENV)/installed
	$(PY) benchmark/launch.py --preset sawyer-cpu

bench-ris-sawyer: $(VENV)/installed
	$(PY) benchmark/speed/bench_ris_sawyer.py
	$(PY) benchmark/figures/sawyer_env.py --out docs/img/sawyer_env.png

bench-hrac: $(VENV)/installed
	$(PY) benchmark/speed/bench_hrac.py
	$(PY) benchmark/figures/hrac_envs.py --out docs/img/hrac_envs.png

clean-venv:
	rm -rf $(VENV)
