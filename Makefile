# Two entry points for a fresh machine:
#   make demo  -- set up .venv, generate the synthetic route, train FDNet (cpu preset), evaluate vs baselines
#   make test  -- set up .venv and run the test suite
#   make test-fast -- the unit tests only (no training, no whole pipelines; tests/conftest.py marks the rest slow)
#   make lint  -- ruff's checks and its layout check (pyproject.toml), which CI runs before make test
#   make format -- lay the code out as make lint expects (ruff format)
# torch is pinned in the same pip command as everything that depends on it, so pip takes the
# CPU wheel and never pulls a multi-GB CUDA build.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
TORCH_PIN := torch==2.13.0
STAMP := $(VENV)/.fdnet-installed

.PHONY: setup demo test test-fast lint format clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	@echo "make: installing torch (CPU) and fdnet's dependencies into $(VENV) (about 2 GB installed; pip shows its progress)"
	$(BIN)/pip install --progress-bar on "$(TORCH_PIN)" -e ".[dev,onnx,hloc]"
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/fdnet demo --out demo-out

test: $(STAMP)
	$(BIN)/python -m pytest -q tests

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP)
	$(BIN)/ruff format .

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow" tests

clean:
	rm -rf $(VENV) demo-out
