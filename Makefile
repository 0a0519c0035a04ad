# Each target bootstraps .venv (created with python3 -m venv, project installed
# editable with its test extras) when it is missing or pyproject.toml changed.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test checks chromium kernels bytecode bench bench-full bench-radio samples venv clean

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	@touch $(STAMP)

venv: $(STAMP)

run: $(STAMP)
	$(BIN)/omniformation run

# lint and type checks first: a finding fails the run before the long suite starts. Chromium's
# install (apt-get, on a fresh machine) goes on beside the venv's and the checks (pip, mypy): one
# does not need the other, and a fresh clone waits for the longer of the two, not for both.
# numba's kernels go into its cache beside them too: on a fresh clone the suite's first processes
# (both halves' pytest and the services they start) would otherwise compile the same kernels side
# by side (a `run` start on an empty cache took 34 CPU-s here, on a full one 5-9).
# The project's own modules are compiled to bytecode once, beside them too: where
# PYTHONDONTWRITEBYTECODE is set (as on these machines) Python never writes a .pyc, so every process
# the suite starts (services, their page processes, emulators, the command line) compiled app/ and
# core/ again: 0.15-0.5 CPU-s a process here (importing app.services.live took 2.28-3.01 CPU-s
# without, 2.10-2.44 with them; test_bad_input.py, test_cli.py and test_session_truth.py, by turns:
# 36 and 35 CPU-s of the machine without, 34 and 35 with). A .pyc older than its source is not used.
test:
	@$(MAKE) --no-print-directory -j3 checks chromium kernels bytecode
	scripts/run-suite

checks: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy

chromium:
	scripts/ensure-chromium

kernels: $(STAMP)
	$(BIN)/python -m app.services.warmup

bytecode: $(STAMP)
	$(BIN)/python -m compileall -q app core tests

# the default families (did this change make it slower? within 5 minutes): one line per figure, the
# services' log and the run's JSON under bench-results/ (`omniformation bench --compare A.json B.json`)
bench: $(STAMP) bench-radio
	$(BIN)/omniformation bench

# every family (the page's floods and clients by turns, the fleet, browsers, sweeps, studies)
bench-full: $(STAMP) bench-radio
	$(BIN)/omniformation bench --full

# what authenticating the radio frames costs the reference firmware (ns per frame, the radio's load)
bench-radio:
	@mkdir -p $(VENV)/build
	cc -std=c99 -Wall -Wextra -Werror -pedantic -O2 firmware/omni_follower.c firmware/mac_bench.c -o $(VENV)/build/mac_bench
	$(VENV)/build/mac_bench

# The sample recordings in recordings/samples (each under 5 MB: one camera frame a second).
samples: $(STAMP)
	for s in paper_simulation experiment2; do \
	  rm -f recordings/samples/$$s-vision.mcap; $(BIN)/omniformation simulate $$s --vision --frames-hz 1 --jpeg-quality 55 \
	    --record recordings/samples/$$s-vision.mcap || exit 1; \
	done

clean:
	rm -rf $(VENV) test-artifacts
