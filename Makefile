# Two commands do all the set-up on a fresh machine:
#   make run    creates .venv, installs orientlab, starts the dashboard with the demo
#               source (the page answers at once; the filters compile in the background,
#               once, and the page says which are ready)
#   make test   creates .venv, installs the test dependencies, runs the whole suite
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
ARGS   ?=

.PHONY: run test bench install generate clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml $(VENV)/.installed
	$(BIN)/pip install -q -e '.[test]'
	touch $@

$(VENV)/.installed-bench: pyproject.toml $(VENV)/.installed-test
	$(BIN)/pip install -q -e '.[test,bench]'
	touch $@

# numba compiles the filters on their first use (30-60 s on 2 cores) and caches the
# result beside the sources: do it here, at install time, in parallel, and again only
# when a source file changed (the cache is per source file).
$(VENV)/.compiled: $(VENV)/.installed $(shell find app -name '*.py' 2>/dev/null)
	$(BIN)/orientlab compile
	touch $@

install: $(VENV)/.compiled

run: $(VENV)/.installed
	$(BIN)/orientlab serve --source demo $(ARGS)

test: $(VENV)/.installed-test $(VENV)/.compiled
	@if [ -z "$$(command -v chromium || command -v chromium-browser || true)" ] && [ ! -x /usr/bin/chromium ]; then \
	  echo; \
	  echo "!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!"; \
	  echo "!!  No Chromium found: the BROWSER TESTS WILL BE SKIPPED.                          !!"; \
	  echo "!!  Install Debian's chromium (apt-get install chromium) to run them.               !!"; \
	  echo "!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!"; \
	  echo; \
	fi
	$(BIN)/python -m pytest -n 2 --dist loadfile $(ARGS)

bench: $(VENV)/.installed-bench
	$(BIN)/python benchmarks/accuracy_phones.py
	$(BIN)/python benchmarks/accuracy_broad.py
	$(BIN)/python benchmarks/gyro_scale.py
	$(BIN)/python benchmarks/heading_drift.py
	$(BIN)/python benchmarks/throughput.py

# the files generated from the parameter definitions (tests/test_config.py and
# tests/test_docs.py fail when either is out of date)
generate: $(VENV)/.installed
	$(BIN)/orientlab params --toml > configs/default.toml
	$(BIN)/python docs/make_parameters.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache tests/artifacts
