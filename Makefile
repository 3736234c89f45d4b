# One-command set-up and entry points. Every target sets up the venv first (idempotent).
#   make demo   - set up and run the live demo on a simulated ICM-20948
#   make test   - set up and run lint + all tests, both tiers (one pytest-xdist worker per core)
#   make test-core - lint + the fast tier: every test that starts no ROS graph (for an edit)
#   make test-ros  - the ros tier alone: the tests that start DDS nodes or ros2 launch
#   make bench  - set up and run the benchmarks (not part of the tests)
#   make fetch-recordings - the public recordings some tests use, outside the repository
#   make stress - the tests RUNS times in a row with every core kept busy (RUNS=20)
#   make colcon-test - colcon build, then the suite through colcon test, as an apt-ROS user runs it

SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
SHARED_DATA ?= ../shared/data

.PHONY: setup demo test test-core test-ros lint stress bench bench-engine bench-replay bench-node \
	bench-recordings bench-broad fetch-recordings colcon-build colcon-test clean

setup: $(STAMP)

$(STAMP): requirements.txt requirements-dev.txt requirements-peers.txt setup.py setup.cfg package.xml scripts/bootstrap_venv.sh
	bash scripts/bootstrap_venv.sh $(VENV)
	$(PY) -m pip install --disable-pip-version-check -q -r requirements-dev.txt
	$(PY) -m pip install --disable-pip-version-check -q --no-deps -r requirements-peers.txt
	$(PY) -m pip install --disable-pip-version-check -q --no-deps -e .
	touch $(STAMP)

demo: setup
	$(VENV)/bin/mag_calibrator_demo

lint: setup
	$(VENV)/bin/ruff check .

test: setup lint
	$(PY) -m pytest -q -n auto --dist loadfile test

test-core: setup lint
	$(PY) -m pytest -q -n auto --dist loadfile -m "not ros" test

test-ros: setup
	$(PY) -m pytest -q -n auto --dist loadfile -m ros test

RUNS ?= 20
stress: setup lint
	$(PY) benchmarks/stress_tests.py --runs $(RUNS) --make

bench: bench-engine bench-replay bench-node

bench-engine: setup
	$(PY) benchmarks/bench_engine.py --data $(SHARED_DATA)

bench-replay: setup
	$(PY) benchmarks/bench_replay.py --data $(SHARED_DATA)

bench-node: setup
	$(PY) benchmarks/bench_node.py

fetch-recordings: setup
	$(PY) scripts/fetch_public_recordings.py

bench-recordings: fetch-recordings
	$(PY) benchmarks/bench_recordings.py --data $(SHARED_DATA)

bench-broad: fetch-recordings
	$(PY) benchmarks/bench_broad.py --json out/bench_broad.json

colcon-build: setup
	source $(VENV)/bin/activate && colcon build --base-paths . --build-base build --install-base install

colcon-test: colcon-build
	source $(VENV)/bin/activate && colcon test --base-paths . --build-base build --install-base install \
		--pytest-args -q -n auto --dist loadfile && colcon test-result --verbose

clean:
	rm -rf build install log .pytest_cache .ruff_cache
