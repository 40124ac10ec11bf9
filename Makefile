# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo test check explore bench lint clean bytecode

# The project's bytecode, compiled ahead (only what changed since): a shell that sets
# PYTHONDONTWRITEBYTECODE (this machine's does) would otherwise compile ~150 modules at every start of
# a command, 0.1-0.17 s of `daror hil` (D177). compileall writes the cache whatever that variable says.
BYTECODE = $(BIN)/python -m compileall -q daror_runtime hal

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# The compiled kernels (numba's cache, beside the sources), compiled at install as the bytecode is,
# on both cores: the identification's validation trajectory run once in a scratch folder (~17 s, of
# which ~13 s compiling the 34 kernels a lock-step run loads) and, beside it, a console session that
# only starts and quits (~11 s: the session's controllers' kernels, which it loads as it opens), then
# a fit of a dataset read from CSV (the reader's kernels, ~2 s). The first `daror identify` after
# install then runs warm (4.7-5.0 s instead of 18.5 s for the training trajectory, D186), and so do
# the first session and the first fit (D197).
DAROR_QUIET = $(BIN)/daror --log-level error
KERNELS = scratch=$$(mktemp -d) && printf 'wait 0.1\nquit\n' > $$scratch/opens.txt \
	&& { { $(DAROR_QUIET) console --script $$scratch/opens.txt --out $$scratch/session --db none \
	&& $(DAROR_QUIET) simulate static --scenario exo_dummy_arm --trajectory validation --out $$scratch/v.csv \
	&& $(DAROR_QUIET) fit plf+ --train $$scratch/v.csv --out $$scratch/plf_plus.json; } > /dev/null & \
	beside=$$!; $(DAROR_QUIET) identify --scenario exo_dummy_arm --trajectory validation \
	--out $$scratch/kernels.npz > /dev/null && wait $$beside; } && rm -rf $$scratch

# The project and its dependencies into the venv: with uv where it can be installed (the same
# resolution and wheels as pip, downloaded in parallel and compiled to bytecode over both cores:
# 33 s against pip's 55 s for everything, D193), with pip otherwise (or when uv fails). The recipe
# sets the shell's `package` (a comma in an argument of `call` would split it) and `pins`
# (constraints, or nothing).
INSTALL = { $(BIN)/python -m pip install --quiet --disable-pip-version-check uv > /dev/null 2>&1 \
	&& $(BIN)/uv pip install --quiet --python $(BIN)/python --compile-bytecode $$pins -e "$$package"; } \
	|| $(BIN)/python -m pip install --quiet --disable-pip-version-check $$pins -e "$$package"
EXTRAS = .[nn,can,dev,ray,web,postgres]
PINS = $(VENV)/pins.txt

# pytest with its rewritten test modules cached (tests/**/__pycache__) whatever the shell says of
# bytecode: rewriting the asserts of the 108 test modules is half of a collection's 10 s of CPU, paid
# again by every later pytest (the mutation run's rows, `make check` after `make test`) without the cache (D193).
PYTEST = PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest

# The runtime alone (what `make demo` needs).
$(VENV)/.installed-base: pyproject.toml | $(BIN)/python
	package=.; pins=; $(INSTALL)
	$(KERNELS)
	touch $@

bytecode: $(VENV)/.installed-base
	$(BYTECODE)

# Everything, optional extras included (what `make test` and `make bench` need). The runtime first,
# then the extras installed while the kernels compile (they need only the runtime; ~12 s saved of a
# fresh clone's `make test`, D207): the extras' install is held to the versions already installed
# (`pins`), so nothing the compiling processes import is replaced under them. Extras that need
# other versions of those packages (a conflict the pins refuse) are installed after the kernels,
# unconstrained, and the kernels compiled again.
$(VENV)/.installed-all: pyproject.toml | $(BIN)/python
	package=.; pins=; $(INSTALL)
	$(BIN)/python -m pip freeze --exclude-editable > $(PINS)
	{ $(KERNELS); } & kernels=$$!; \
	package='$(EXTRAS)'; pins='-c $(PINS)'; { $(INSTALL); } > $(VENV)/pinned-install.log 2>&1; installed=$$?; \
	wait $$kernels || exit 1; \
	if [ $$installed -ne 0 ]; then \
		echo "make: the extras need other versions of installed packages: installing them, then the kernels again"; \
		package='$(EXTRAS)'; pins=; $(INSTALL) && $(KERNELS); \
	fi
	touch $@ $(VENV)/.installed-base

demo: $(VENV)/.installed-base bytecode
	$(BIN)/daror demo

# System packages the tests use: can-utils (log2asc reads the HIL bus log). Without them the tests
# that need them are skipped with the reason; nothing else depends on them.
$(VENV)/.system-packages: | $(BIN)/python
	@command -v log2asc >/dev/null 2>&1 || { \
		(apt-get update -qq && apt-get install -y -qq can-utils) >/dev/null 2>&1 \
		|| echo "make: can-utils could not be installed; the log2asc test will be skipped"; }
	touch $@

# PostgreSQL's server programs (the records' tests start a private cluster with them on a Unix
# socket, tests/postgres_server.py; Debian's own service is not used), installed only when initdb is
# missing; without them the PostgreSQL half of those tests is skipped with the reason.
$(VENV)/.postgresql: | $(BIN)/python
	@{ command -v initdb >/dev/null 2>&1 || ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1; } || { \
		(apt-get update -qq && apt-get install -y -qq postgresql) >/dev/null 2>&1 \
		|| echo "make: postgresql could not be installed; the records' PostgreSQL tests will be skipped"; }
	touch $@

# Chromium and its driver (the web console's browser test, tests/daror_runtime/console/test_web_console.py), installed
# only when /usr/bin/chromium or /usr/bin/chromedriver is missing; without them that test is skipped.
$(VENV)/.chromium: | $(BIN)/python
	@{ test -x /usr/bin/chromium && test -x /usr/bin/chromedriver; } || { \
		(apt-get update -qq && apt-get install -y -qq chromium chromium-driver) >/dev/null 2>&1 \
		|| echo "make: chromium could not be installed; the web console's browser test will be skipped"; }
	touch $@

# The whole suite (CI), over both cores in one run: whole files per worker, the longest first
# (tests/conftest.py; xdist would otherwise reorder them by their number of tests, D202), and the
# tests that need wall-clock time (marker realtime) as one unit handed out first: one worker runs
# them one after another, each measuring the machine's margin before it runs (docs/testing.md),
# while the other runs the longest file, so at most one busy process of the suite is beside them
# (D208). The slowest tests are printed: CI's log says where the time went.
test: $(VENV)/.installed-all $(VENV)/.system-packages $(VENV)/.chromium $(VENV)/.postgresql bytecode
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(PYTEST) -n 2 --dist loadgroup --no-loadscope-reorder --durations=30

# The fast tier, a developer's loop: everything but the slow, subprocess, browser, mutation and
# real-time tests.
check: $(VENV)/.installed-all bytecode
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(PYTEST) -n 2 -m "not slow and not subprocess and not browser and not mutation and not realtime" --durations=40

# New random examples for every property test (five times CI's count where a test does not set its
# own): CI's draws are fixed (D192); run this to look further, and keep what it finds as an @example.
explore: $(VENV)/.installed-all bytecode
	HYPOTHESIS_PROFILE=explore $(PYTEST) -n 2 -m "not subprocess and not browser and not mutation and not realtime"

bench: $(VENV)/.installed-all bytecode
	$(BIN)/daror bench --json bench_out/latest.json

lint: $(VENV)/.installed-all
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

clean:
	rm -rf $(VENV) demo_out bench_out .pytest_cache .ruff_cache .hypothesis
