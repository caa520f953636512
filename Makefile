# The two commands a newcomer needs:  make demo  and  make test  (make test-quick: the fast subset, while editing)
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.gtforge-installed

.PHONY: setup demo test test-quick bench clean

$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh $(VENV)
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)  ## set up, then run calibrate -> validate -> calibrate-scale -> refine -> build-dataset -> evaluate on synthetic data, then gtforge run (the dataset certificate)
	$(VENV)/bin/gtforge demo demo_out

# test processes side by side (pytest-xdist); the synthetic sessions are rendered once and shared (tests/conftest.py).
# With a process per core, BLAS threads and OpenMP threads that spin while they wait only take the other process's
# core: one BLAS thread each, and OpenMP's waiting threads sleep (benchmarks/RESULTS.md, "The test suite's time")
TEST_WORKERS ?= 2
TEST_ENV := OPENBLAS_NUM_THREADS=1 OMP_WAIT_POLICY=passive

test: $(STAMP)  ## set up, lint, then run the whole test suite, printing the 15 slowest tests (what CI runs: .ci/run)
	$(VENV)/bin/ruff check src tests benchmarks scripts
	$(TEST_ENV) $(PY) -m pytest -n $(TEST_WORKERS) --durations=15

test-quick: $(STAMP)  ## set up, then run the tests not marked slow (about a minute on a 2-core VM)
	$(TEST_ENV) $(PY) -m pytest -n $(TEST_WORKERS) -m "not slow"

bench: $(STAMP)  ## benchmarks (ratios against baselines measured in the same run; tables in benchmarks/RESULTS.md)
	$(PY) benchmarks/bench_reproject.py
	$(PY) benchmarks/bench_calibrate.py
	$(PY) benchmarks/bench_encodings.py
	$(PY) benchmarks/bench_writes.py
	$(PY) benchmarks/profile_scene.py
	$(PY) benchmarks/profile_startup.py
	$(PY) benchmarks/bench_build_dataset.py

clean:
	rm -rf demo_out .pytest_cache
