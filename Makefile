# The README's two commands: `make demo` and `make test`. Both create .venv and install the project.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export WANDB_MODE ?= offline
DEMO_DIR ?= demo_out

.PHONY: install demo test test-slow browser bench clean

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null || { echo "needs $(PYTHON) (pybullet ships wheels for 3.11)"; exit 1; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev,gpu-physics,launchers]'  # gpu-physics: MuJoCo Warp, so its tests run too; launchers: hydra/launcher=parallel|slurm
	touch $(STAMP)

install: $(STAMP)

# rooms → a few minutes of tiny-model training → sampling → evaluation, printed side by side
demo: install
	$(BIN)/python -m spread.cli.demo --out $(DEMO_DIR)

test: install
	WANDB_MODE=disabled $(BIN)/python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder --durations=15

# the browser tests (tests/test_browser.py) drive Debian's headless chromium; installed here when missing
browser:
	@command -v chromium >/dev/null || command -v chromium-browser >/dev/null || \
	  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver; } || \
	  { echo "needs chromium (Debian: apt-get install chromium chromium-driver) for the browser tests"; exit 1; }

test-slow: install browser
	WANDB_MODE=disabled $(BIN)/python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder -m slow

bench: install
	$(BIN)/python benchmarks/bench_generate.py

clean:
	rm -rf $(DEMO_DIR) .pytest_cache
