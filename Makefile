# mimucal: set-up, demo, tests. Works on a fresh machine with Python 3.11 alone.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(VENV)/bin/pip
DEMO   ?= demo-output
STAMP  := $(VENV)/.installed

.PHONY: setup demo test test-fast lint browser reproduce bench clean

$(STAMP): pyproject.toml requirements.lock
	$(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet --upgrade pip
	$(PIP) install --quiet -c requirements.lock -e ".[dask,test]"
	touch $(STAMP)

setup: $(STAMP)

# Debian's chromium for the browser tests of the HTML reports (skipped when absent).
browser:
	bash tools/install-browser.sh

demo: setup
	rm -rf $(DEMO)
	$(VENV)/bin/mimucal simulate $(DEMO)/dataset --lots 2 --units 8 --reps 5 --seed 7 --rate 50 \
		--outliers 1 --bad-sessions 1
	# exit code 1 is expected: the demo fleet has one bad session on purpose
	$(VENV)/bin/mimucal nightly $(DEMO)/dataset --results $(DEMO)/results --unit-reports \
		|| [ $$? -eq 1 ]
	@echo "Lot reports: $$(ls $(DEMO)/results/reports/*.html 2>/dev/null | tr '\n' ' ')"
	@echo "Unit reports: $$(ls $(DEMO)/results/reports/units/*.html 2>/dev/null | wc -l) in $(DEMO)/results/reports/units/"

# --dist loadfile: a module's tests share one worker, so module fixtures (a 60-unit fleet,
# a browser, a Prefect API) are built once, not once per worker. --no-loadscope-reorder keeps
# the collection order tests/conftest.py gives: the longest modules first.
# The browser install is best effort here (no root: the browser tests skip and say why);
# CI installs it first and must succeed (.ci/run).
test: setup
	-bash tools/install-browser.sh
	$(VENV)/bin/pytest -q -n 2 --dist loadfile --no-loadscope-reorder --durations=15

test-fast: setup
	$(VENV)/bin/pytest -q -n 2 --dist loadfile -m "not slow and not browser and not server"

# ruff check + format check, no rewriting ([tool.ruff] in pyproject.toml)
lint: setup
	bash tools/lint.sh

reproduce: setup
	$(VENV)/bin/mimucal reproduce xu2016
	$(VENV)/bin/mimucal reproduce zhang2017

# make bench BENCH_ARGS=--quick: the few-minute development version (docs/benchmarks.md)
bench: setup
	$(PY) -m benchmarks.run $(BENCH_ARGS)

clean:
	rm -rf $(VENV) $(DEMO) .pytest_cache
