# The README's two commands are `make run` and `make test`; both install what they need.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
SAMPLE  := sample_data/sample.mcap
RUN_DIR := runs/sample

.PHONY: install run test lint sample bench clean

# System library that open3d needs (`import open3d` fails without libusb).
$(VENV)/.syslibs:
	@if ! ldconfig -p | grep -q libusb-1.0.so.0; then \
		echo "installing libusb-1.0-0 (needed by open3d)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0; \
	fi
	@mkdir -p $(VENV) && touch $@

$(STAMP): pyproject.toml $(VENV)/.syslibs
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[dev]"
	@touch $@

install: $(STAMP)

run: $(STAMP)
	$(BIN)/surgrecon run $(SAMPLE) -o $(RUN_DIR) --export mcap
	@echo "report: $(abspath $(RUN_DIR))/report.html"
	@echo "Foxglove: open $(abspath $(RUN_DIR))/export.mcap, import $(abspath $(RUN_DIR))/export.layout.json"

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m mypy
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m mypy

# Regenerates the shipped sample bit-for-bit (same seed, same encoder).
sample: $(STAMP)
	$(BIN)/surgrecon simulate $(SAMPLE) --seed 7

bench: $(STAMP)
	$(BIN)/python -m pip install -q -e ".[bench]"
	$(BIN)/python benchmarks/registration.py

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache .mypy_cache
