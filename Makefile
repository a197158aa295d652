# Two commands on a fresh machine: `make demo` and `make test`. Everything else is a helper.
SHELL := /bin/bash
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
# Test workers: one per core of the CI machine (2). Each test file runs whole on one worker
# (--dist loadfile), so a file's fixtures, fake cameras and ptys are never shared between workers;
# the longest files start first (tests/conftest.py; xdist's reordering by test count is off).
TEST_WORKERS ?= 2
# Extra pytest arguments for a one-off run, e.g. make test PYTEST_ARGS="--durations=0".
PYTEST_ARGS ?=
STAMP := $(VENV)/.installed

.PHONY: setup llvm aravis-debs aravis chromium demo test bench lint clean

setup: $(STAMP) llvm aravis chromium

# $(call install,SPEC): the project (or an extra of it) into the venv. With uv when pip could
# fetch it — it installs the ~75 packages in ~5 s where pip takes ~30 s (measured on a fresh clone,
# both from warm caches; docs/performance.md), the largest part of `make test`'s setup — and with
# pip where uv is absent or fails (uv reads PyPI only, not a machine's pip config: a machine whose
# packages come only from its own index gets pip). Both resolve pyproject.toml alone: the same
# versions (pip freeze of the two venvs, compared). The pip config on some machines lists absent
# local indexes; only those warnings are hidden.
# --compile-bytecode: uv, unlike pip, writes no .pyc of what it installs, and where
# PYTHONDONTWRITEBYTECODE is set (as on the machines docs/performance.md measures) no process
# writes one either, so each of the suite's ~250 Python processes compiled every third-party
# module it imported from source again: 9.7 against 3.7 CPU-s to import a fit's and a
# reduction's modules (measured). Compiling the venv once costs ~40 CPU-s (~20 s on 2 cores).
pip = set -o pipefail; $(BIN)/python -m pip install --quiet $(1) 2>&1 | { grep -v "^WARNING: Location" || true; }
install = { test -x $(BIN)/uv && \
  $(BIN)/uv pip install --quiet --compile-bytecode --python $(BIN)/python $(1); } || \
  { $(call pip,$(1)); }

# Reinstall only when the dependency list changes.
$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(call pip,--upgrade pip)
	@$(call pip,uv) || echo "note: could not install uv; installing with pip (slower)"
	@echo "installing gonio and its dependencies into $(VENV)"
	@$(call install,-e '.[dev]')
	@touch $(STAMP)

# Mitsuba's llvm_ad_rgb variant needs libLLVM >= 17 (15/16 abort the process). Debian 12 ships
# libllvm19. Install it when we are root and it is missing; otherwise the code falls back to
# scalar_rgb and says so once.
llvm:
	@if ls /usr/lib/*/libLLVM.so.19* /usr/lib/*/libLLVM-1[7-9]*.so* >/dev/null 2>&1; then \
	  :; \
	elif [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	  echo "installing libllvm19 for Mitsuba's llvm variant"; \
	  (apt-get install -y -qq libllvm19 >/dev/null 2>&1 || \
	   (apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq libllvm19 >/dev/null 2>&1)) || \
	  echo "note: could not install libllvm19; Mitsuba will use scalar_rgb"; \
	else \
	  echo "note: libLLVM >= 17 not found and not root; Mitsuba will use scalar_rgb"; \
	fi

# The Aravis camera backend and its tests: Debian's Aravis 0.8 (the GI typelib and the
# arv-fake-gv-camera-0.8 GigE Vision simulator the tests start on 127.0.0.1), plus the headers
# PyGObject builds against. Installed as root like libllvm19. Where that is impossible the
# reason goes to $(VENV)/.aravis-unavailable: then, and only then, the Aravis tests skip
# (tests/support/aravis.py); otherwise a missing library is a test failure.
ARAVIS_DEBS := aravis-tools gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev
ARAVIS_MARK := $(VENV)/.aravis-unavailable
have_aravis_debs = command -v arv-fake-gv-camera-0.8 >/dev/null && \
  ls /usr/lib/*/girepository-1.0/Aravis-0.8.typelib >/dev/null 2>&1 && \
  pkg-config --exists gobject-introspection-1.0 cairo

aravis-debs:
	@if $(have_aravis_debs); then \
	  :; \
	elif [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	  echo "installing Aravis 0.8 for the GenICam camera backend ($(ARAVIS_DEBS))"; \
	  (DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(ARAVIS_DEBS) >/dev/null 2>&1 || \
	   (apt-get update -qq >/dev/null 2>&1 && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(ARAVIS_DEBS) >/dev/null 2>&1)) || \
	  echo "note: could not install $(ARAVIS_DEBS); the Aravis tests will skip"; \
	else \
	  echo "note: Aravis 0.8 not found and not root; the Aravis tests will skip"; \
	fi

# PyGObject in the venv (built against the system's girepository, ~1 min, once; cached after).
aravis: $(STAMP) aravis-debs
	@if ! ($(have_aravis_debs)); then \
	  echo "Debian packages missing: $(ARAVIS_DEBS) (make setup installs them as root)" > $(ARAVIS_MARK); \
	elif $(BIN)/python -c 'import gi; gi.require_version("Aravis", "0.8")' 2>/dev/null; then \
	  rm -f $(ARAVIS_MARK); \
	else \
	  echo "building PyGObject for the Aravis backend (about a minute, once)"; \
	  if $(call install,-e '.[aravis]'); then \
	    rm -f $(ARAVIS_MARK); \
	  else \
	    echo "could not build PyGObject (gonio[aravis])" > $(ARAVIS_MARK); \
	    echo "note: could not build PyGObject; the Aravis tests will skip"; \
	  fi; \
	fi

# Headless Chromium checks that report.html renders (tests/support/browser.py): no console error, every
# image decoded, a screenshot kept. Installed as root like the others; where that is impossible
# the reason goes to $(CHROMIUM_MARK) and then, and only then, the browser tests skip.
CHROMIUM_MARK := $(VENV)/.chromium-unavailable
chromium: $(STAMP)
	@if command -v chromium >/dev/null; then \
	  rm -f $(CHROMIUM_MARK); \
	elif [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	  echo "installing chromium to check the HTML report in a real browser (about a minute, once)"; \
	  (DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null 2>&1 || \
	   (apt-get update -qq >/dev/null 2>&1 && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null 2>&1)) && \
	  rm -f $(CHROMIUM_MARK) || \
	  { echo "apt-get could not install chromium" > $(CHROMIUM_MARK); \
	    echo "note: could not install chromium; the report's browser check will skip"; }; \
	else \
	  echo "chromium not found and not root" > $(CHROMIUM_MARK); \
	  echo "note: chromium not found and not root; the report's browser check will skip"; \
	fi

demo: setup
	$(BIN)/gonio demo

# The sources are byte-compiled once before the suite starts its ~250 Python processes: where
# PYTHONDONTWRITEBYTECODE is set (as on the machine docs/performance.md measures) no process
# writes a .pyc, and each one compiled the ~42k lines it imports again (0.2 CPU-s a process,
# measured); compileall redoes only what changed since. One OpenBLAS thread per test worker: two
# workers already fill the two cores, and OpenBLAS's spinning threads only slow both
# (tests/conftest.py says how much).
PACKAGES := acquisition brdfdata calibration fitting gonio plumbing simulator tools tests
test: setup
	$(BIN)/ruff check .
	$(BIN)/lint-imports
	$(BIN)/python -m compileall -q -j 2 $(PACKAGES) > /dev/null
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile \
	  --no-loadscope-reorder --durations=25 $(PYTEST_ARGS)

# The peers (JAX, NumPyro) are an optional extra: without them the peer benchmarks say so in
# one line and the rest run.
bench: setup
	@$(call install,-e '.[bench]') || \
	  echo "note: could not install the bench extra (jax, numpyro); peer comparisons are skipped"
	$(BIN)/python benchmarks/run_all.py $(BENCH)

lint: setup
	$(BIN)/ruff check . && $(BIN)/ruff format --check .

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .hypothesis
