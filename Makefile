# Two commands on a fresh machine: `make train` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# One torch thread per process unless the caller says otherwise (2-core machine).
export OMP_NUM_THREADS ?= 1
export MUJOCO_GL ?= egl
# Test workers (pytest-xdist): one per core by default; each test file runs whole on
# one worker, so its module fixtures are built once. TEST_WORKERS=0: one process.
TEST_WORKERS ?= auto

.PHONY: install test test-fast train lint bench gpu-check clean

install: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# torch first and pinned: an unpinned torch would pull a multi-GB CUDA build.
	$(PY) -m pip install --quiet -c constraints.txt torch
	# the extras the test suite exercises: the SLURM launcher (its local executor), Ray
	$(PY) -m pip install --quiet -c constraints.txt -e ".[dev,slurm,ray]"
	touch $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile

test-fast: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m "not slow"

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

train: $(STAMP)
	$(PY) train.py experiment=quickstart

# every benchmarks/bench_*.py (tests/test_benchmarks.py runs each at tiny sizes)
bench: $(STAMP)
	for script in benchmarks/bench_*.py; do $(PY) $$script || exit 1; done

# the prepared device check (benchmarks/gpu_check.py): on a CUDA machine the device tests
# and a short training on the GPU eager and captured beside the CPU eager (three trainings,
# sized for one call of a lent machine; the script alone runs every mode); without CUDA
# one line, exit 0
gpu-check: $(STAMP)
	$(PY) benchmarks/gpu_check.py --modes eager captured

clean:
	rm -rf $(VENV) outputs multirun .pytest_cache
