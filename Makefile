# Two commands on a fresh machine with Python 3.11: `make run` and `make test`.
# Each creates .venv and installs the project into it when needed.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
# make run SCENARIO=scenarios/smoke.yaml OUT=out/smoke: another scenario, another folder
SCENARIO ?= scenarios/valley.yaml
OUT ?= out/$(basename $(notdir $(SCENARIO)))

.PHONY: run test bench venv clean

$(STAMP): pyproject.toml setup.py robot_sim/native/pinocchio_inplace.cpp
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade "pip>=24,<27"
	$(BIN)/python -m pip install --quiet -e ".[test,cluster]"
	touch $(STAMP)

venv: $(STAMP)

# The main job: the thesis' valley experiment end to end over Zenoh -
# 6 demonstrations, learning with BIC, 20 reproductions, report (out/valley/).
# Its last line sums the run up; it exits non-zero when the run failed.
run: $(STAMP)
	$(BIN)/etar-bench run $(SCENARIO) --out $(OUT)

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python bench/etar_fit.py
	$(BIN)/python bench/sim_step.py

clean:
	rm -rf $(VENV) out .pytest_cache
