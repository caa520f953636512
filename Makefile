# The two commands a newcomer needs:  make demo  and  make test
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.gtforge-installed

.PHONY: setup demo test bench clean

$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh $(VENV)
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)  ## set up, then run calibrate -> validate -> refine -> build-dataset -> evaluate on synthetic data
	$(VENV)/bin/gtforge demo demo_out

test: $(STAMP)  ## set up, then run the test suite
	$(PY) -m pytest

bench: $(STAMP)  ## benchmarks (ratios against baselines measured in the same run; tables in benchmarks/RESULTS.md)
	$(PY) benchmarks/bench_reproject.py
	$(PY) benchmarks/bench_calibrate.py
	$(PY) benchmarks/bench_encodings.py
	$(PY) benchmarks/bench_writes.py
	$(PY) benchmarks/profile_scene.py
	$(PY) benchmarks/bench_build_dataset.py

clean:
	rm -rf demo_out .pytest_cache
