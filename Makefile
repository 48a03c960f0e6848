# The two commands a newcomer needs: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
DEMO   := demo-out

.PHONY: demo test install install-test bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

# Installs are re-run only when pyproject.toml changes (stamp files).
$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e '.[test]'
	touch $@ $(VENV)/.installed

install: $(VENV)/.installed
install-test: $(VENV)/.installed-test

# The nightly job end to end on an embedded default: a simulated drive log, built in a
# local work directory; prints a short summary.
demo: install
	rm -rf $(DEMO)
	$(BIN)/mosaicmap simulate floor $(DEMO)/logs/day1 --seed 1 --area 5x5 --quiet
	$(BIN)/mosaicmap build $(DEMO)/logs/day1 --workdir $(DEMO)/work --report $(DEMO)/report.json --quiet
	$(BIN)/python -m pipeline.summary $(DEMO)/report.json

test: install-test
	$(BIN)/python -m pytest -n 2 -q

# The benchmarks behind the README's figures (a few minutes; the drone set takes most).
bench: install
	$(BIN)/python bench/bench_ingest.py
	$(BIN)/python bench/bench_register.py
	$(BIN)/python bench/bench_optimize.py
	$(BIN)/python bench/bench_real.py

clean:
	rm -rf $(VENV) $(DEMO) *.egg-info
