# relief-bsdf: two commands do everything on a fresh clone.
#   make demo   create .venv (Python 3.11), install the pinned dependencies, run the default job
#   make test   same venv plus the test-only oracles, run the whole test suite
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
OUT    ?= out

.PHONY: demo test venv venv-test bench extension clean help

help:
	@echo "make demo | make test | make bench | make extension | make clean"

$(VENV)/.runtime-stamp: requirements/runtime.txt backend/pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet --upgrade pip
	$(PIP) install --quiet -r requirements/runtime.txt
	$(PIP) install --quiet --no-deps -e backend
	@touch $@

$(VENV)/.test-stamp: $(VENV)/.runtime-stamp requirements/test.txt
	$(PIP) install --quiet -r requirements/test.txt
	@touch $@

venv: $(VENV)/.runtime-stamp
venv-test: $(VENV)/.test-stamp

demo: venv
	$(VENV)/bin/relief synth --kind gaussian --rms-height-um 0.5 --corr-length-um 10 --size 256 --pitch-um 1 --seed 1 -o $(OUT)/demo/relief.npz
	$(VENV)/bin/relief info $(OUT)/demo/relief.npz
	$(VENV)/bin/relief fit scenes/demo/sample.toml -o $(OUT)/demo/fit --max-iter 40
	@if [ -f $(OUT)/demo/fit/fit.json ]; then src=$(OUT)/demo/fit; else src=scenes/demo/sample.toml; fi; \
	  echo "relief render $$src -o $(OUT)/demo/plate.png"; $(VENV)/bin/relief render $$src -o $(OUT)/demo/plate.png

test: venv-test
	$(PY) -m pytest

bench: venv
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

extension: venv
	$(PY) relief_addon/build_extension.py --out dist

clean:
	rm -rf $(OUT) dist .pytest_cache
