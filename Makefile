# Two entry points do all set-up on a fresh machine:
#   make forecast   -> the weekly San Francisco forecast (offline-capable defaults)
#   make test       -> the test suite
# Both create or refresh .venv (torch==2.13.0 CPU wheel first) and the system packages.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.flowcast-installed

.PHONY: forecast test venv sysdeps bench clean-venv

$(STAMP): pyproject.toml Makefile
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

sysdeps:
	bash scripts/install-system-deps.sh

forecast: venv sysdeps
	$(VENV)/bin/flowcast forecast

test: venv sysdeps
	$(VENV)/bin/python -m pytest -q

bench: venv
	$(VENV)/bin/python -m bench.run_all

clean-venv:
	rm -rf $(VENV)
