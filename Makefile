# Two-command set-up: `make demo` and `make test` (README). Both create .venv when missing.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
export QT_QPA_PLATFORM ?= offscreen
# Small-matrix numerics: one BLAS thread avoids contention on 2-core machines (see app/__init__.py).
export OPENBLAS_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1

.PHONY: demo test lint bench constraints clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): $(BIN)/python pyproject.toml constraints.txt
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/pelvislab demo --out demo-output

lint: $(STAMP)
	$(BIN)/ruff check .

# One test process per core (pytest-xdist): the gap diagnoses dominate the suite and their
# serial parts (base fits) left a core idle; worksteal evens out the minute-long tests.
test: lint
	$(BIN)/python -m pytest -q -n logical --dist worksteal

BENCH_STAMP := $(VENV)/.installed-bench-stamp

$(BENCH_STAMP): $(STAMP)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[test,bench]'
	touch $(BENCH_STAMP)

bench: $(BENCH_STAMP)
	$(BIN)/python -m pelvislab.tests.benchmarks

# Re-pin after a deliberate dependency change.
constraints: $(STAMP)
	( printf '# Pinned versions of every dependency (runtime and test), so a fresh install next month\n# resolves the same set. Regenerate with: make constraints\n'; \
	  $(BIN)/python -m pip freeze --exclude-editable | grep -vi '^pelvislab' ) > constraints.txt

clean:
	rm -rf $(VENV) build *.egg-info demo-output
