# Two commands: `make demo` and `make test`. Each creates .venv and installs sfmloc when missing.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test test-deps lint format typecheck bench bench-publish proto clean

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev,bench]'
	@touch $(STAMP)

demo: $(STAMP)
	$(BIN)/sfmloc demo

# ruff runs first (seconds), then the suite with mypy beside it: mypy (~25 s without its cache,
# one core) on the second core while the suite's first tests run (mostly one core: OMP/BLAS
# pinned to one thread) instead of before them. mypy's findings are printed after the suite and
# fail the run; when it finds none, pytest's summary stays the last line. test-deps installs
# the browser the viewer's test uses, where it can (never fails).
#
# The suite runs in TEST_JOBS processes (pytest-xdist; 2 = this machine's cores), each test file
# whole on one process (--dist loadfile: a file's module fixtures, its servers and maps, are
# built once, and its tests never run beside each other). `make test TEST_JOBS=0` runs it in
# this one process, as plain pytest (pdb, -x, print debugging; PYTEST_ADDOPTS adds options).
TEST_JOBS ?= 2
test: test-deps lint $(STAMP)
	@echo "$(BIN)/mypy --cache-dir $(VENV)/.mypy_cache (beside the suite; findings after it)"
	@$(BIN)/mypy --cache-dir $(VENV)/.mypy_cache > $(VENV)/mypy.log 2>&1 & mypy=$$!; \
	$(BIN)/python -m pytest -q -n $(TEST_JOBS) --dist loadfile; rc=$$?; \
	if ! wait $$mypy; then cat $(VENV)/mypy.log; echo "make test: mypy failed" >&2; rc=1; fi; \
	exit $$rc

# What the tests need beyond Python: Debian's chromium for the viewer's browser test
# (tests/test_viewer.py). Never fails: where it cannot install (no root, not Debian), it says so
# and that test is skipped with the reason.
test-deps:
	@command -v chromium >/dev/null 2>&1 \
	|| { apt-get update -qq && apt-get install -y -qq chromium; } \
	|| echo "make test-deps: chromium not installed (apt-get install -y chromium needs root" \
	"and Debian's packages); the viewer's browser test will be skipped" >&2

# Style and likely bugs: ruff at the configured width with import order (pyproject [tool.ruff]).
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check --quiet .

# Rewrite the tree to the style `make lint` checks: format, safe fixes (import order, ...), and
# string literals split where the formatter leaves lines over 100 columns.
format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix --exit-zero --quiet .
	$(BIN)/python tools/split_long_strings.py $$(git ls-files '*.py' ':!:client/sfmloc_client/pb')
	$(BIN)/ruff format .

# Types of all of sfmloc and sfmloc_client (pyproject [tool.mypy]); cache in .venv.
typecheck: $(STAMP)
	$(BIN)/mypy --cache-dir $(VENV)/.mypy_cache

# All suites (redkitchen needs ../shared/data); prints the summary and its wall time.
bench: $(STAMP)
	@start=$$(date +%s); $(BIN)/sfmloc bench --out bench-out; rc=$$?; \
	echo "make bench: $$(( $$(date +%s) - start )) s (exit $$rc)"; exit $$rc

# Commit a bench run's numbers: docs/results.json (compact: the run's indented file is over
# test_bench's 200 kB bound) and the README's results block from it.
bench-publish: $(STAMP)
	mkdir -p docs
	$(BIN)/python -c "import json, sys; json.dump(json.load(open(sys.argv[1])), \
	open(sys.argv[2], 'w'), separators=(',', ':'))" bench-out/results.json docs/results.json
	$(BIN)/python -m sfmloc.bench.readme docs/results.json README.md

# Regenerate the committed gRPC/protobuf code from proto/ (tests fail when it is stale).
proto: $(STAMP)
	$(BIN)/python proto/generate.py

clean:
	rm -rf $(VENV) build *.egg-info
