# histojax: `make demo` and `make test` set themselves up in .venv.
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo lint test test-all test-integrations integrations bench bench-histogym bench-large reference-quick contract fuzz fuzz-cohort clean bench-gpu test-min

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "need $(PYTHON) (Python 3.11) on PATH, or run: make PYTHON=python3 ..."; exit 1; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,lint,features,dicom,openslide]'
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m baselines.demo

# ruff (pyproject.toml's [tool.ruff]): the lint rules, then the formatter's check (it changes no file;
# `.venv/bin/ruff format .` formats the tree); .ci/run runs this before `make test`
lint: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

# two pytest workers, one test file each at a time (module fixtures built once): 6 min instead of 9 on 2 cores
TEST_WORKERS ?= 2
PYTEST := $(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile

test: $(STAMP)
	$(PYTEST)

# HISTOJAX_TEST_ALL=1: the hypothesis tests draw their full example counts (tests/hypothesis_examples.py)
test-all: integrations
	HISTOJAX_TEST_ALL=1 $(PYTEST) -m ''

# Stable-Baselines3 (with torch, heavy) and rejax: not in `make test`'s install; their tests skip without them
integrations: $(STAMP)
	$(PY) -m pip install --quiet -e '.[sb3,rejax]'

test-integrations: integrations
	$(PY) -c "import stable_baselines3, rejax"  # the tests below skip without them: fail here instead
	$(PY) -m pytest -q -rs tests/adapters/test_sb3.py tests/adapters/test_rejax.py tests/adapters/test_gymnax.py tests/adapters/test_gymnasium.py

# the lowest declared versions (requirements-min.txt = pyproject.toml's floors) in their own venv, core tests
MIN_VENV := .venv-min
MIN_TESTS ?= tests/env/test_env.py tests/env/test_properties.py tests/training/test_ppo_and_dqn.py tests/reading/test_diagnosis.py tests/project/test_min_versions.py
test-min:
	test -x $(MIN_VENV)/bin/python || $(PYTHON) -m venv $(MIN_VENV)
	$(MIN_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(MIN_VENV)/bin/python -m pip install --quiet -e '.[test]' -c requirements-min.txt
	$(MIN_VENV)/bin/python -m pip check
	$(MIN_VENV)/bin/python -m pytest -q $(MIN_TESTS)

fuzz: $(STAMP)
	HISTOJAX_FUZZ_EXAMPLES=10000 $(PY) -m pytest -q -s tests/hostile_inputs/test_fuzz.py

# the cohort path's targets only (labels CSV, --shard strings, imported .h5 features), 10,000 cases each
fuzz-cohort: $(STAMP)
	HISTOJAX_FUZZ_EXAMPLES=10000 $(PY) -m pytest -q -s tests/hostile_inputs/test_fuzz.py -k "labels_csv or shard or feature_h5"

bench: $(STAMP)
	$(PY) benchmarks/throughput.py

# every GPU figure, one process, an internal 8-minute budget (docs/benchmarks.md#gpu-figures)
GPU_OUT ?= benchmarks/results/gpu
bench-gpu: $(STAMP)
	$(PY) benchmarks/gpu.py --out $(GPU_OUT)

bench-histogym: $(STAMP)
	$(PY) -m pip install --quiet -e '.[bench]'
	$(PY) benchmarks/vs_histogym.py

bench-large: $(STAMP)
	$(PY) benchmarks/large_slide.py --size 100000 --compare-sample

# a small slice of the C16 reference table and of the budget curve (small variant built on the fly;
# minutes on 2 CPU cores)
reference-quick: $(STAMP)
	$(PY) -m experiments.c16_reference --quick --out runs/c16-reference-quick
	$(PY) -m baselines.reading.budget_curve --dataset runs/c16-reference-quick/data/c16-small-pcam \
	  --env HistoJAX-C16-Diagnosis-v1 --glimpse-level 2 --seeds 3 --out runs/c16-reference-quick/budget-curve

contract: $(STAMP)
	$(PY) -m histojax.testing

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
