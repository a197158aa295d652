# Two commands on a fresh machine: `make demo` and `make test`. Everything else is a helper.
SHELL := /bin/bash
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup llvm demo test bench lint clean

setup: $(STAMP) llvm

# Reinstall only when the dependency list changes.
$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	@# The pip config on some machines lists absent local indexes; hide only those warnings.
	set -o pipefail; $(BIN)/python -m pip install --quiet --upgrade pip 2>&1 | { grep -v "^WARNING: Location" || true; }
	set -o pipefail; $(BIN)/python -m pip install --quiet -e '.[dev]' 2>&1 | { grep -v "^WARNING: Location" || true; }
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

demo: setup
	$(BIN)/gonio demo

test: setup
	$(BIN)/ruff check .
	$(BIN)/lint-imports
	$(BIN)/python -m pytest -q

bench: setup
	$(BIN)/python benchmarks/run_all.py $(BENCH)

lint: setup
	$(BIN)/ruff check . && $(BIN)/ruff format --check .

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .hypothesis
