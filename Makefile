# Two commands on a fresh machine with Python 3.11: `make run` and `make test`.
# Each creates .venv and installs the project into it when needed (and compiles numba's
# kernels once: services/run/kernel_cache.py).

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
# make run SCENARIO=scenarios/smoke.yaml OUT=out/smoke: another scenario, another folder
SCENARIO ?= scenarios/valley.yaml
OUT ?= out/$(basename $(notdir $(SCENARIO)))

.PHONY: run test test-fast bench venv clean browser foxglove-schemas foxglove-studio

$(STAMP): pyproject.toml setup.py robot_sim/arm/native/pinocchio_inplace.cpp kernel_plumbing/native/json_numbers.cpp
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade "pip>=24,<27"
	$(BIN)/python -m pip install --quiet --no-compile -e ".[test,cluster]"
	@# pip byte-compiles one file at a time (half of the install); compileall does it on every
	@# core, the project's own modules too, which an editable install leaves to each process
	@# (every one, where PYTHONDONTWRITEBYTECODE is set); a file that does not compile is
	@# compiled at its import, as after pip, which ignores them too.  Left out: what no process of
	@# the project imports (pip, setuptools, the libraries' own test suites, and PyOpenGL, which
	@# only MuJoCo's viewer uses: a third of the files), compiled at its import if ever
	$(BIN)/python -m compileall -q -j 0 -x '/(OpenGL|pip|setuptools|tests?)/' $(VENV)/lib etar kernel_plumbing \
	  robot_sim services tests >/dev/null || true
	$(BIN)/python -m services.run.kernel_cache
	touch $(STAMP)

venv: $(STAMP)

# The main job: the thesis' valley experiment end to end over Zenoh -
# 6 demonstrations, learning with BIC, 20 reproductions, report (out/valley/).
# Its last line sums the run up; it exits non-zero when the run failed.
run: $(STAMP)
	$(BIN)/etar-bench run $(SCENARIO) --out $(OUT) --replace

# Set-up in two chains at once (-j 2): the venv (pip, bytecode, numba: CPU) beside what the
# browser tests need (apt, npm: mostly the network).  Then the lanes (tests/lanes.py says
# how): the `alone` tests one at a time, then the other `serial` ones one at a time with the
# rest two at a time beside them.  Any lane failing (or finding no test) fails the target.
test:
	@$(MAKE) --no-print-directory -j 2 $(STAMP) foxglove-studio
	@$(BIN)/python -m tests.lanes

# the fast lane: every test but the slow ones (whole scenarios, runs over Zenoh, compose)
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow"

# the browser test renders report.html in Debian's chromium: installed when missing and
# this runs as root with apt; elsewhere that one test is skipped (it says why)
browser:
	@command -v chromium >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && \
	  { apt-get install -y -qq --no-install-recommends chromium >/dev/null 2>&1 || \
	    { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq --no-install-recommends chromium >/dev/null 2>&1; }; }; } || \
	  echo "note: chromium is not installed; the test that renders report.html in a browser is skipped"

# Foxglove's own JSON Schemas (@foxglove/schemas from npm) for the test that validates every
# visual message against them: npm (apt's nodejs and npm when missing and this runs as
# root) installs them under .cache/; elsewhere that test is skipped (it says why)
FOXGLOVE_SCHEMAS := .cache/foxglove-schemas
# after `browser`: one apt-get at a time (two at once, the second finds dpkg's lock taken)
foxglove-schemas: browser
	@test -f $(FOXGLOVE_SCHEMAS)/jsonschema/VERSION || { \
	  { command -v npm >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && \
	    { apt-get install -y -qq --no-install-recommends nodejs npm >/dev/null 2>&1 || \
	      { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq --no-install-recommends nodejs npm >/dev/null 2>&1; }; }; }; } && \
	  npm install --silent --no-audit --no-fund --prefix $(FOXGLOVE_SCHEMAS) @foxglove/schemas@2.1.0 >/dev/null 2>&1 && \
	  node tests/foxglove/dump_schemas.js $(FOXGLOVE_SCHEMAS)/jsonschema; } || \
	  echo "note: @foxglove/schemas could not be installed from npm; the test that validates the visual messages against it is skipped"

# Foxglove Studio 1.48, the last open-source release, as the app @foxglove/studio-base ships
# prebuilt, with React 17 and playwright-core, for the test that opens a recording in it
# (tests/services/foxglove/test_foxglove_studio.py; chromium from `browser`); elsewhere it is skipped
FOXGLOVE_STUDIO := .cache/foxglove-studio
foxglove-studio: foxglove-schemas
	@test -f $(FOXGLOVE_STUDIO)/READY || { \
	  command -v npm >/dev/null 2>&1 && mkdir -p $(FOXGLOVE_STUDIO)/studio-base && \
	  (cd $(FOXGLOVE_STUDIO) && npm pack --silent @foxglove/studio-base@1.48.0 >/dev/null 2>&1 && \
	   tar xzf foxglove-studio-base-1.48.0.tgz -C studio-base && rm foxglove-studio-base-1.48.0.tgz) && \
	  npm install --silent --no-audit --no-fund --prefix $(FOXGLOVE_STUDIO) react@17.0.2 react-dom@17.0.2 \
	    playwright-core@1.65.1 >/dev/null 2>&1 && touch $(FOXGLOVE_STUDIO)/READY; } || \
	  echo "note: Foxglove Studio 1.48 could not be installed from npm; the test that opens a recording in it is skipped"

bench: $(STAMP)
	$(BIN)/python bench/etar_fit.py
	$(BIN)/python bench/sim_step.py

clean:
	rm -rf $(VENV) out .pytest_cache
