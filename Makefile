# Two commands do all the set-up on a fresh machine:
#   make serve   create .venv, install LoopNet, seed the weights cache, run the service
#   make test    the same set-up, then the whole test suite
PYTHON ?= python3.11
VENV ?= .venv
SHARED ?= ../shared
BIN := $(VENV)/bin

.PHONY: install weights serve test lint bench

$(BIN)/loopnet: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --upgrade pip
	$(BIN)/pip install -e '.[dev]'
	touch $@

install: $(BIN)/loopnet

# Offline machines: link the verified weights into $$TORCH_HOME/hub/checkpoints.
weights: install
	@if [ -d "$(SHARED)/weights" ]; then $(BIN)/loopnet weights seed "$(SHARED)/weights"; \
	else echo "no $(SHARED)/weights: weights download on first use"; fi

serve: weights
	$(BIN)/loopnet serve

test: install
	LOOPNET_SHARED_DIR="$(SHARED)" $(BIN)/python -m pytest

lint: install
	$(BIN)/ruff check service workers migrations tests benchmarks
	$(BIN)/ruff format --check service workers migrations tests benchmarks

bench: weights
	$(BIN)/python benchmarks/stage_latency.py --image "$(SHARED)/data/gardenspoint_first10/query/0.jpg"
