# parflow: setup, test, run, benchmark.  Environment: scripts/env.sh (the only place).
#
#   make setup                      apt packages (if missing) + .venv + editable install
#   make test [TEST_JOBS=n]         pytest serial (on n processes, default: the cores), then
#                                   under mpirun -n 2; fails if either fails
#   make run [SCENE=x.toml] [ARGS=...] [NP=2]
#                                   mpirun -n $(NP) python -m parflow.shear $(SCENE) $(ARGS)
#                                   (ARGS defaults to --overwrite: make run can be repeated;
#                                   Ctrl-C / kill stop it with a checkpoint: docs/output.md "Signals")
#   make bench                      every benchmarks/bench_*.py with the venv python
#   make clean                      remove .venv and caches (not out/ or runs/)

SHELL := /bin/bash
.SHELLFLAGS := -euo pipefail -c
.DEFAULT_GOAL := help

VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.parflow-setup-stamp
ENV    := . scripts/env.sh &&

NP          ?= 2
SCENE       ?=
ARGS        ?= --overwrite
PYTEST_ARGS ?=
# the cores this process may use (nproc obeys OMP_NUM_THREADS, which scripts/env.sh sets to 1)
TEST_JOBS   ?= $(shell env -u OMP_NUM_THREADS -u OMP_THREAD_LIMIT nproc 2>/dev/null || echo 1)

.PHONY: help setup test test-serial test-mpi run bench clean

help:
	@sed -n '1,/^$$/p' Makefile | sed 's/^# \{0,1\}//'

setup: $(STAMP)

# Re-run the setup when the project metadata or the setup itself changes.
$(STAMP): pyproject.toml scripts/setup.sh scripts/env.sh
	bash scripts/setup.sh

# Both runs always happen; the target fails if either fails.  Exit code 5 from pytest
# ("no tests collected") is a failure like any other non-zero code.
test: $(STAMP)
	@rc=0; \
	echo "== pytest (serial) =="; \
	$(MAKE) --no-print-directory test-serial || rc=1; \
	echo "== pytest (mpirun -n $(NP)) =="; \
	$(MAKE) --no-print-directory test-mpi || rc=1; \
	if [ $$rc -ne 0 ]; then echo "make test: FAILED (see above)"; else echo "make test: serial and mpirun -n $(NP) passed"; fi; \
	exit $$rc

# The serial session runs on TEST_JOBS processes (pytest-xdist, one test file per process at
# a time: a file's fixtures are built once) when xdist is installed and TEST_JOBS > 1;
# TEST_JOBS=1 runs it in one process, as without xdist.
test-serial: $(STAMP)
	$(ENV) jobs=$(TEST_JOBS); \
	if [ "$$jobs" -gt 1 ] && $(PY) -c 'import xdist' 2>/dev/null; then \
	  set -- -n "$$jobs" --dist loadfile; else set --; fi; \
	$(PY) -m pytest "$$@" tests $(PYTEST_ARGS)

# No cache plugin under MPI: all ranks would write .pytest_cache at the same time.
# mpirun hands the ranks a pseudo-terminal, so decide on colour from make's own stdout.
test-mpi: $(STAMP)
	$(ENV) mpirun -n $(NP) $(PY) -m pytest -p no:cacheprovider \
	  --color=$$([ -t 1 ] && echo yes || echo no) tests $(PYTEST_ARGS)

# scripts/mpirun-parflow: mpirun that relays SIGTERM / Ctrl-C to the ranks, which end the step
# under way, write a checkpoint and exit 143 / 130 (bare mpirun would kill them after 1 s).
# exec: make sends SIGTERM to its child, which must be the launcher, not an intermediate shell.
run: $(STAMP)
	$(ENV) exec scripts/mpirun-parflow -n $(NP) $(PY) -m parflow.shear $(SCENE) $(ARGS)

bench: $(STAMP)
	@$(ENV) shopt -s nullglob; files=(benchmarks/bench_*.py); \
	if [ $${#files[@]} -eq 0 ]; then echo "no benchmarks/bench_*.py yet"; exit 0; fi; \
	rc=0; for f in "$${files[@]}"; do \
	  echo "== $$f =="; $(PY) "$$f" || { echo "FAILED: $$f"; rc=1; }; \
	done; exit $$rc

clean:
	rm -rf $(VENV) .pytest_cache *.egg-info
	find . -path ./.git -prune -o -type d -name __pycache__ -prune -exec rm -rf {} +
