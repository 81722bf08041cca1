# ekf_vo: every target creates its own virtual environment and installs what it needs.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test test-quick bench bench-quick venv params clean

venv: $(STAMP)

$(STAMP): requirements.txt requirements-test.txt setup.py
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -r requirements-test.txt
	$(BIN)/pip install --quiet --no-deps -e .
	touch $(STAMP)

## The main job: play the bundled bag through vo_node + map_node over DDS, print the summary.
demo: $(STAMP)
	$(BIN)/ekf-vo-demo --out out/demo

## All tests (those needing the developers' data folder skip with a reason when it is absent).
test: $(STAMP)
	$(BIN)/python -m pytest -q test

## The tests without the slow ones (colcon build, wheel build): a quick check while editing.
test-quick: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow" test

## Regenerate config/ekf_vo.yaml from the typed parameter definitions (ekf_vo/config.py).
params: $(STAMP)
	$(BIN)/ekf-vo-params --yaml > config/ekf_vo.yaml

## Every benchmark, the full report in bench/results (committed).
bench: $(STAMP)
	$(BIN)/python -m bench.run_all --out bench/results

## The reduced benchmarks into out/bench-quick (ignored): the committed report is untouched.
bench-quick: $(STAMP)
	$(BIN)/python -m bench.run_all --quick --out out/bench-quick

clean:
	rm -rf $(VENV) build install log out .pytest_cache
