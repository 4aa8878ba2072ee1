# Two commands for a new user: `make demo` and `make test`.
# Everything is installed into .venv, created on first use from the system python3.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: demo test bench install clean help

help:
	@echo "make demo   create .venv if missing, install, run an emulated skin and the daemon, press, show the contact"
	@echo "make test   create .venv if missing, install cellbridge into it, run the test suite"
	@echo "make bench  run the benchmarks in bench/ and print their tables"
	@echo "make clean  remove .venv and build leftovers"

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip "setuptools>=77" wheel
	$(PY) -m pip install --quiet -e ".[test,plot]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/cellbridge demo

test: $(STAMP)
	$(PY) -m pytest -q

bench: $(STAMP)
	@for f in bench/bench_*.py; do echo "== $$f"; $(PY) $$f || exit 1; done

clean:
	rm -rf $(VENV) build dist *.egg-info .pytest_cache .hypothesis
