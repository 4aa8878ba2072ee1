# Two commands for a new user: `make demo` and `make test`.
# Everything is installed into .venv, created on first use from the system python3.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: demo test test-fast lint bench install tools clean help

# Programs the views' tests drive (tmux for `cellbridge watch`, Debian's chromium for
# `cellbridge web`), and what the C subscriber example's test builds it with (a compiler,
# make, pkg-config, the libzmq and msgpack-c headers): installed with apt-get when missing
# and this runs as root; else their tests skip and say why.
TOOLS := tmux chromium
# pkg-config names (any of, comma-separated) -> Debian package of the C example's libraries
C_LIBS := libzmq:libzmq3-dev msgpack-c,msgpack:libmsgpack-dev

help:
	@echo "make demo   create .venv if missing, install, run an emulated skin and the daemon, press, show the contact"
	@echo "make test   create .venv if missing, install cellbridge into it (and tmux/chromium as root), lint, run the test suite"
	@echo "            on TEST_JOBS workers (default 2; TEST_JOBS=0: one process)"
	@echo "make test-fast  the tests that start no process and no pty and take no seconds of CPU each"
	@echo "            (-m 'not process and not slow'), in one process: a quick check while working (make test runs all)"
	@echo "make lint   ruff (pyproject's [tool.ruff]) and mypy ([tool.mypy], through .ci/typecheck); make test runs it first"
	@echo "make bench  run the benchmarks in bench/ and print their tables"
	@echo "make clean  remove .venv and build leftovers"

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip "setuptools>=77" wheel
	$(PY) -m pip install --quiet -e ".[test,plot,robot,ros2]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/cellbridge demo

tools:
	@missing=""; for t in $(TOOLS); do command -v $$t >/dev/null 2>&1 || missing="$$missing $$t"; done; \
	command -v cc >/dev/null 2>&1 || missing="$$missing gcc libc6-dev"; \
	command -v make >/dev/null 2>&1 || missing="$$missing make"; \
	command -v pkg-config >/dev/null 2>&1 || missing="$$missing pkg-config"; \
	for l in $(C_LIBS); do found=""; for n in $$(echo $${l%%:*} | tr , ' '); do \
	  pkg-config --exists $$n 2>/dev/null && found=1; done; [ -n "$$found" ] || missing="$$missing $${l#*:}"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "installing$$missing (apt-get) for the views' and the C example's tests"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq$$missing fonts-dejavu-core >/dev/null \
	      || echo "could not install$$missing: their tests will skip"; \
	  else echo "missing$$missing (not root or no apt-get): their tests will skip"; fi; \
	fi

# Lint and type-check first: a finding fails `make test` before the suite runs.
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	.ci/typecheck $(PY)

# The suite runs on TEST_JOBS pytest-xdist workers (default 2: half its time is real
# processes waiting on real time; its timing tests are built to pass with both cores busy).
# `make test TEST_JOBS=0` runs it in one process, as `pytest` alone does.
# --dist worksteal: each worker starts on one half of the collection, in its order, and a
# worker that runs out takes the back half of what the other still has queued. A module's
# tests mostly run on one worker, and its module-scoped set-up (a live skin, a pressed daemon,
# a virtual skin's run) is made once. pytest-xdist's default (load) hands out runs of tests
# in turn, ever shorter toward the end, so a module could have its tests and its set-up on
# both workers; and a worker it had handed a long run of slow tests late kept them while the
# other ran out of work (load takes nothing back). Stealing evens the two out to the end.
TEST_JOBS ?= 2

# The numba kernels compile into their cache (about 30 s of one core on a fresh checkout) while
# lint runs on the other: the suite then starts with them cached, and is told so
# (CELLBRIDGE_KERNELS_WARMED: tests/conftest.py's warm-up, the same as this one, which a
# pytest started by hand runs, is not done a second time). A background job of this shell
# ignores Ctrl-C (SIGINT: a non-interactive shell's jobs do), so the trap stops it with the rest.
test: $(STAMP) tools
	@$(PY) tests/support/warm_kernels.py & warm=$$!; \
	trap 'kill $$warm 2>/dev/null; exit 130' INT TERM; \
	$(MAKE) --no-print-directory lint; status=$$?; wait $$warm; exit $$status
	CELLBRIDGE_KERNELS_WARMED=1 $(PY) -m pytest -q -n $(TEST_JOBS) --dist worksteal

# The fast lane: every test that stays in this process (tests/conftest.py marks those that
# start a process or a pty `process`, and fails an unmarked one that does), on one worker.
test-fast: $(STAMP)
	$(PY) -m pytest -q -n 0 -m "not process and not slow"

bench: $(STAMP)
	@for f in bench/bench_*.py; do echo "== $$f"; $(PY) $$f || exit 1; done

clean:
	rm -rf $(VENV) build dist *.egg-info .pytest_cache .hypothesis .mypy_cache .ruff_cache
