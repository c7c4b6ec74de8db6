# Two entry points do all set-up on a fresh machine:
#   make forecast   -> the weekly San Francisco forecast (offline-capable defaults)
#   make test       -> the test suite
# and `make hub` (= make forecast FORECAST_ARGS="--hub covid"): this week's CDC COVID-19
# Forecast Hub round; `make hub HUB=flu` FluSight's, `make hub HUB=rsv` the RSV hub's.
# Both create or refresh .venv (torch==2.13.0 CPU wheel first) and the system packages.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.flowcast-installed
# torch's OpenMP threads spin-wait by default, which stalls 2-thread ops on a busy 2-core box.
export OMP_WAIT_POLICY := PASSIVE

.PHONY: forecast hub test variants venv sysdeps bench clean-venv

# Bytecode: each module is compiled the first time a process imports it, and written for the
# processes after. PYTHONDONTWRITEBYTECODE (set on this VM and in CI) would make every process
# compile torch, prefect, pandas, ... again (about 20 s of CPU each), so the targets unset it.
# The venv is not compiled ahead: compileall over site-packages took 56 s on 2 cores, mostly
# modules nothing imports.
unexport PYTHONDONTWRITEBYTECODE
# --no-build-isolation: the package builds with the venv's own setuptools and wheel (installed
# beside torch) instead of a throw-away build environment made on every install.
# pip first: the pip that venv bundles (23.2.1 with Python 3.11.7) spends most of the install
# weighing each of the 133,000 files the indexes list for the project's 180 packages; on this
# 2-core VM the install after torch took 55 s and 40 s with it, 33 s and 25 s with pip 26.3.
$(STAMP): pyproject.toml Makefile
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --no-compile 'pip>=25.1'
	$(PY) -m pip install --quiet --no-compile torch==2.13.0 'setuptools>=68' wheel
	$(PY) -m pip install --quiet --no-compile --no-build-isolation -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

sysdeps:
	bash scripts/install-system-deps.sh

# Archived DataSF exports used to seed an empty cache when DataSF cannot be reached. Only the
# three datasets the forecast reads (cases gyr2-k29z, deaths g2di-xufg, tests nfpa-mg4g): the
# archive also holds other exports (vaccinations, ...) that `flowcast data import` rejects.
ARCHIVE ?= ../shared/data/datasf
ARCHIVE_FILES = -name 'COVID-19_Cases_Over_Time.csv' -o -name 'COVID-19_Deaths_Over_Time.csv' \
                -o -name 'Covid-19_Tests.csv'

# Archived CDPH county downloads (six vintages of every California county): the published
# forecast's pooled members learn from the counties beside San Francisco, and the nowcast's delay
# model is fitted from the vintages (pipeline/forecast/nowcasting.py; with fewer than two the run
# drops the last 14 days instead). They are recorded real vintages whose one revision beyond the
# policy (Los Angeles 2020-06-21, docs/data.md) was reviewed, hence --accept-revisions;
# --if-empty imports them only into a cache without CDPH data.
CDPH_ARCHIVE ?= ../shared/data/cdph

# The CDC COVID-19 Forecast Hub's data (every NHSN/NSSP vintage of its time series): imported
# into an empty cache so that a hub round runs offline (live, the run fetches data.cdc.gov).
NHSN_ARCHIVE ?= ../shared/data/nhsn

forecast: venv sysdeps
	@if [ -d "$(ARCHIVE)" ]; then \
	  $(VENV)/bin/flowcast data import --if-empty \
	    $$(find "$(ARCHIVE)" \( $(ARCHIVE_FILES) \) | sort); fi
	@if [ -d "$(CDPH_ARCHIVE)" ]; then \
	  $(VENV)/bin/flowcast data import --if-empty --accept-revisions \
	    $$(find "$(CDPH_ARCHIVE)" -name covid19cases_test.csv | sort); fi
	@if [ -f "$(NHSN_ARCHIVE)/time-series.parquet" ]; then \
	  $(VENV)/bin/flowcast data import --if-empty "$(NHSN_ARCHIVE)/time-series.parquet"; fi
	PREFECT_SERVER_ANALYTICS_ENABLED=false DO_NOT_TRACK=1 \
	  FLOWCAST_CDPH_ARCHIVE=$${FLOWCAST_CDPH_ARCHIVE:-$(CDPH_ARCHIVE)} \
	  $(VENV)/bin/flowcast forecast $(FORECAST_ARGS)

# Each hub's data (every vintage of its time series) imported into an empty cache first, so
# that its round runs offline; live, the run fetches data.cdc.gov.
HUB ?= covid
HUB_ARCHIVE_covid = $(NHSN_ARCHIVE)
HUB_ARCHIVE_flu = ../shared/data/flusight
HUB_ARCHIVE_rsv = ../shared/data/rsv
hub: venv
	@if [ -f "$(HUB_ARCHIVE_$(HUB))/time-series.parquet" ]; then \
	  $(VENV)/bin/flowcast data import --if-empty "$(HUB_ARCHIVE_$(HUB))/time-series.parquet"; fi
	$(MAKE) forecast FORECAST_ARGS="--hub $(HUB) $(FORECAST_ARGS)"

# The type check (pyright over pipeline/ and flows/, settings in pyproject.toml: zero errors)
# beside the tests, in the time the test workers wait on servers and sockets; its report follows
# theirs, and either failing fails the target. The tests go as whole files to two workers (a
# file's module fixtures are built once), longest files first (the order tests/conftest.py
# collects them in; xdist's own reorder by test count is off).
test: venv sysdeps
	@$(VENV)/bin/pyright > $(VENV)/pyright.log 2>&1 & types=$$!; \
	$(VENV)/bin/python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder; tests=$$?; \
	wait $$types; typed=$$?; echo "pyright:"; cat $(VENV)/pyright.log; \
	test $$tests -eq 0 -a $$typed -eq 0

# The report's Table 5 columns beyond the run's own model: train the paper's variants once
# (Dask workers, flows/scale_out.py); the weekly forecast scores every variant in the model cache.
variants: venv
	PREFECT_SERVER_ANALYTICS_ENABLED=false DO_NOT_TRACK=1 \
	  $(VENV)/bin/python -m flows.scale_out --variants transformer-ke mamba $(VARIANT_ARGS)

bench: venv
	for b in simulate training smc paper_tables e2e backtest; do \
	  $(VENV)/bin/python -m bench.$$b || exit 1; done

clean-venv:
	rm -rf $(VENV)
