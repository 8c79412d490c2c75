# Two commands on a fresh machine with Python 3.11: `make run` and `make test`.
# Each creates .venv and installs the project into it when needed.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
OUT ?= out

.PHONY: run test bench venv clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade "pip>=24,<27"
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $(STAMP)

venv: $(STAMP)

# The main job.  Until the simulator and services land (issues 3 and 4) it runs
# the learning stage on synthetic demonstrations: demonstrate -> learn (BIC) -> report.
run: $(STAMP)
	$(BIN)/etar synth --out $(OUT)/demos --demos 6 --length 600 --phases 3 --seed 0
	$(BIN)/etar learn $(OUT)/demos/*.npz --phases auto --out $(OUT)/model.json
	$(BIN)/etar inspect $(OUT)/model.json --demos $(OUT)/demos/*.npz

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python bench/etar_fit.py

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache
