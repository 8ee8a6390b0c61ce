# torchcal: `make demo` and `make test` set everything up on a fresh clone.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup demo check test rounding bench clean

setup: $(STAMP)

# torch first, pinned to the CPU wheel that is on disk here; the package itself only asks torch>=2.2.
# Ray and rosbags (optional extras for users) are installed here so that the fleet's Ray test and
# the ROS bag tests run
$(STAMP): pyproject.toml Makefile
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e '.[dev,ray,ros]'
	touch $(STAMP)

demo: setup
	$(BIN)/python scripts/demo.py --out out/demo

# the fast lane, on every change: unit and contract tests, no test marked slow (<= 90 s on 2 cores)
check: setup
	$(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not slow"

# everything (what CI runs): two processes, one test file each at a time (module fixtures stay in
# one process): CI has two cores
test: setup
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

# the rounding-sensitive files under MKL's AVX2 and COMPATIBLE modes, torch's AVX2 kernels, and
# one and two threads (issue 34): no test may depend on which kernel rounds last
rounding: setup
	PYTHON=$(BIN)/python scripts/rounding_check.sh

bench: setup
	$(BIN)/python scripts/bench_fk.py

clean:
	rm -rf out .pytest_cache
