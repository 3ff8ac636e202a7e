# Brasidas: every target installs what it needs first (idempotently).
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP_APT := $(VENV)/.apt-stamp
STAMP_PIP := $(VENV)/.pip-stamp
# The JavaScript packages (package-lock.json): uPlot, served by the station, ESLint, and the
# tests' real Foxglove WebSocket client (@foxglove/ws-protocol + ws).
STAMP_NPM := node_modules/.npm-stamp

APT_PACKAGES := python3 python3-venv python3-dev gcc pkg-config \
	libgirepository1.0-dev libcairo2-dev gir1.2-gstreamer-1.0 gir1.2-gst-plugins-base-1.0 \
	gir1.2-gst-rtsp-server-1.0 gstreamer1.0-tools gstreamer1.0-plugins-base \
	gstreamer1.0-plugins-good gstreamer1.0-plugins-bad gstreamer1.0-plugins-ugly \
	gstreamer1.0-libav gstreamer1.0-x iproute2 chromium chromium-headless-shell libjs-leaflet

.PHONY: demo test test-quick bench lint deps apt venv clean net-demo soak

deps: $(STAMP_APT) $(STAMP_PIP) $(STAMP_NPM)

# Node from Debian only when there is no npm at all (a machine with another Node keeps it).
$(STAMP_NPM): package.json package-lock.json | $(STAMP_APT)
	@command -v npm >/dev/null || { echo "installing Debian packages: nodejs npm"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends nodejs npm; }
	npm ci --no-audit --no-fund --loglevel=error
	@touch $@

# Debian packages: installed only when one is missing (looked at again when this file changes).
$(STAMP_APT): Makefile
	@missing=$$(for p in $(APT_PACKAGES); do dpkg-query -W -f='$${Status}\n' $$p 2>/dev/null | grep -q '^install ok installed' || echo $$p; done); \
	if [ -n "$$missing" ]; then \
		echo "installing Debian packages:" $$missing; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $$missing; \
	fi
	@mkdir -p $(VENV) && touch $@

$(STAMP_PIP): pyproject.toml | $(STAMP_APT)
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test,bench]'
	# GTSAM (the pose graph): its 4.3.0 wheel declares pytest>=9, which no module of it imports
	# and which clashes with pytest-asyncio<1; numpy, its one real dependency, is above.
	$(PY) -m pip install -q --no-deps 'gtsam==4.3.0'
	@touch $@


demo: deps
	$(PY) -m stationd.demo

# The test network by hand (root): namespaces, a station and two --sim platforms, one link to impair.
net-demo: deps
	$(PY) -m brasidas.netem

# Not in CI: 30 minutes of 20 Hz teleop at 2 % loss on the test network (root), figures at the end.
soak: deps
	$(PY) -m bench.soak --minutes 30

# Parallel workers (pytest-xdist): the suite mostly waits on sockets, processes and Chromium
# (a 2-worker run used 0.7 of its 2 cores): 4 workers, two a core here (8 min at 2, ~5 at 4).
# The tests that failed at 4 on a loaded machine were fixed at their cause. A test sharing a
# module's rig keeps to one worker; browser tests run in BROWSER_LANES lanes of one worker
# each (tests/support/markers.py). `make test TEST_WORKERS=0` runs it in one process.
TEST_WORKERS ?= 4
BROWSER_LANES ?= 1
export BROWSER_LANES
PYTEST := $(PY) -m pytest -q -p no:cacheprovider --durations=15 -n $(TEST_WORKERS) --dist loadgroup
# Bytecode caches written even where the environment says not to (PYTHONDONTWRITEBYTECODE=1, as
# in this machine's shell): without them every worker rewrote and compiled all 160 test modules
# (~5 CPU s each) and every platform process compiled its modules again, on every run. Here that
# was 16 s of a 4-worker run's start (28 s with no caches, 12 s with them).
test test-quick: export PYTHONDONTWRITEBYTECODE :=
# A tree with none of them yet (a fresh clone) has its test modules rewritten and compiled once,
# in one process, before the workers start: each worker would do all of it at the same time
# (a fresh start here: 39 s, against 10 s for this and 20 s for the workers then).
WARM_CACHES := $(if $(filter-out 0,$(TEST_WORKERS)),@ls tests/__pycache__/*-pytest-*.pyc >/dev/null 2>&1 \
	|| $(PY) -m pytest -q -p no:cacheprovider --collect-only >/dev/null 2>&1 || true)

test: deps
	$(WARM_CACHES)
	$(PYTEST)

# The quick set (no browser, network namespace, interop or other slow tests): under a minute.
test-quick: deps
	$(WARM_CACHES)
	$(PYTEST) -m "not slow"

# `make bench console`: only the benchmarks named after `bench` (no-op goals of their own).
BENCH_NAMES := $(if $(filter bench,$(MAKECMDGOALS)),$(filter-out bench,$(MAKECMDGOALS)))
bench: deps
	$(PY) -m bench $(BENCH_NAMES)
ifneq ($(BENCH_NAMES),)
$(BENCH_NAMES): ; @:
endif

lint: deps
	$(VENV)/bin/ruff check brasidas platformd stationd tests bench
	$(VENV)/bin/ruff format --check brasidas platformd stationd tests bench
	$(VENV)/bin/mypy
	node_modules/.bin/eslint web

clean:
	rm -rf $(VENV) build *.egg-info
