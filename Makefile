# Two commands: `make demo` and `make test`. Both bootstrap .venv on first use.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: test demo lint bench bench-real experiment schemas clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev,plot]'
	# compile the numba kernels once (~10 s) so services and tests start warm
	$(PY) -c "from service.core.warmup import warm_up; print(f'numba kernels ready in {warm_up():.1f} s')"
	touch $(STAMP)

test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(PY) -m pytest

demo: $(STAMP)
	$(PY) -m sim_publisher.demo

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# Benchmarks are the modules of the bench package: `python -m bench.bench_x` from this folder.
# bench_kidnap (kidnaps on the real logs, ~8 min; reads /work/shared/data/real) is left out
# of `bench` too: `python -m bench.bench_kidnap --trials 20 --jobs 2`.
# bench_real is left out of `bench`: the whole matrix on the three real logs takes well over
# an hour (its 36 runs took 97 min of run time at load 1-5 on 2 cores, 18-22 min each for shape
# without odometry on the intel and fr079 schematic maps); run it on its own with `make bench-real` (reads /work/shared/data/real), e.g.
# `make bench-real BENCH_REAL_ARGS="--jobs 2 --resume"` to finish an interrupted run.
BENCH_REAL_ARGS ?=
bench: $(STAMP)
	for b in bench/bench_*.py; do \
		m=$$(basename $$b .py); \
		case $$m in bench_real|bench_kidnap) continue;; esac; \
		$(PY) -m bench.$$m || exit 1; \
	done

bench-real: $(STAMP)
	$(PY) -m bench.bench_real $(BENCH_REAL_ARGS)

experiment: $(STAMP)
	$(VENV)/bin/shapeloc-sim experiment

schemas: $(STAMP)
	$(PY) -m schemas.export

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache build *.egg-info
