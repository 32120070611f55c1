# relief-bsdf: two commands do everything on a fresh clone.
#   make demo   create .venv (Python 3.11), install the pinned dependencies, run the default job
#   make test   same venv plus the test-only oracles and the docs tools: build the docs, run the whole test suite
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
OUT    ?= out

.PHONY: demo test test-fast docs lint-imports venv venv-test venv-docs bench extension clean help

help:
	@echo "make demo | make test | make test-fast | make docs | make lint-imports | make bench | make extension | make clean"

# the editable install also builds the optional compiled ray kernels in place (backend/setup.py)
$(VENV)/.runtime-stamp: requirements/runtime.txt backend/pyproject.toml backend/setup.py \
                        backend/src/relief_bsdf/kernels/_compiled.pyx
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet --upgrade pip
	$(PIP) install --quiet -r requirements/runtime.txt
	$(PIP) install --quiet --no-deps -e backend
	@touch $@

$(VENV)/.test-stamp: $(VENV)/.runtime-stamp requirements/test.txt requirements/docs.txt
	$(PIP) install --quiet -r requirements/test.txt
	@touch $@

# the docs need only mkdocs (requirements/docs.txt), not the runtime
$(VENV)/.docs-stamp: requirements/docs.txt
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet -r requirements/docs.txt
	@touch $@

venv: $(VENV)/.runtime-stamp
venv-test: $(VENV)/.test-stamp
venv-docs: $(VENV)/.docs-stamp

demo: venv
	$(VENV)/bin/relief info scenes/demo/relief.x3p
	$(VENV)/bin/relief info scenes/demo/sample.toml
	$(VENV)/bin/relief fit scenes/demo/sample.toml -o $(OUT)/demo/fit --max-iter 40
	$(VENV)/bin/relief render $(OUT)/demo/fit -o $(OUT)/demo/plate.png
	@echo "demo done: $(OUT)/demo/fit/report.html (fit), $(OUT)/demo/plate.png (before | after)"

# the manual (docs/, mkdocs.yml) into site/; --strict: any warning (a broken link or anchor, a page left out of the nav) fails
docs: venv-docs
	$(PY) -m mkdocs build --strict --quiet --site-dir site

# the layering contract (pyproject.toml [tool.importlinter], docs/architecture.md): every import, those inside
# functions too; --no-cache: no cache folder in the checkout
lint-imports: venv-test
	$(VENV)/bin/lint-imports --config pyproject.toml --no-cache

# the whole suite on both cores (pytest-xdist; worksteal: the long physics checks do not queue behind one worker)
test: venv-test docs lint-imports
	$(PY) -m pytest -n 2 --dist worksteal

# day-to-day tier: everything not marked slow, on both cores (worksteal: an idle worker takes queued tests
# from the busy one, so both end together); each test process gets its share of the cores (tests/conftest.py)
test-fast: venv-test
	$(PY) -m pytest -m "not slow" -n 2 --dist worksteal

bench: venv
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

extension: venv
	$(PY) relief_addon/build_extension.py --out dist

clean:
	rm -rf $(OUT) dist site .pytest_cache
