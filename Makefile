# Two entry points (see README): `make demo` and `make test`. Both set up an isolated
# environment (.venv) on a fresh machine first; nothing needs to be installed by hand.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export PIP_DISABLE_PIP_VERSION_CHECK := 1

.PHONY: demo test setup system-deps browser lint bench clean

# Open3D's wheel needs libusb-1.0 and libgomp from the OS; install them when we can (root + apt).
system-deps:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo ">> installing libusb-1.0-0 libgomp1 (needed by open3d)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 libgomp1 >/dev/null; \
	  else echo "!! please install libusb-1.0-0 (needed by open3d)"; fi; \
	fi

$(STAMP): pyproject.toml
	@$(MAKE) --no-print-directory system-deps
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[dev,baselines,calib,cluster,loops,ray]"
	# MapClosures (the loop benchmark's competitor, its tests): map-closures 2.2 declares numpy<2.3
	# but runs on the numpy above; --no-deps so it cannot downgrade it (its own deps are installed)
	$(PY) -m pip install -q --no-deps "map-closures>=2.0,<3"
	@touch $(STAMP)

setup: $(STAMP)

# Headless Chromium for the browser test of the interactive 3D view (Debian package).
browser:
	@if ! command -v chromium >/dev/null; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo ">> installing chromium (browser test of the 3D view)"; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null || echo "!! chromium not installed: browser test will skip"; \
	  fi; \
	fi

demo: $(STAMP)
	$(VENV)/bin/graffmatch demo

# Two pytest workers, one per core of the CI machine, each taking whole test files (tests of one
# file share compiled kernels and fixtures): 631 s -> 445 s on a fresh clone, numba compiling.
test: $(STAMP) browser
	$(PY) -m pytest -q -p no:cacheprovider -n 2 --dist loadfile

lint: $(STAMP)
	$(VENV)/bin/ruff check graffmatch tests bench

bench: $(STAMP)
	$(PY) bench/bench_solver.py
	$(PY) bench/bench_matcher.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
