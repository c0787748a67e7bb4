# The README's two commands: `make run` (train + evaluate + report the default recipe) and `make test` (ruff's
# format check and lint, then the test suite on one pytest-xdist worker per core, up to 4, `--dist worksteal`: the
# tests are shared out and an idle worker takes queued ones from a busy worker, so a file's module fixtures may be
# built on more than one; .ci/run runs it). Both create .venv on first use and install the project with the exact
# versions in constraints.txt. `make format` applies ruff's formatting and safe fixes.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
RECIPE ?= quickstart
ARGS   ?=

.PHONY: install run test format clean

install: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	# torch first, by exact version: the CPU wheel, never a CUDA build pulled in by a loose requirement.
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -c constraints.txt -e ".[dev]"
	touch $(STAMP)

run: $(STAMP)
	MUJOCO_GL=egl $(BIN)/adarl run $(RECIPE) $(ARGS)

test: $(STAMP)
	$(BIN)/ruff format --check .
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q -n auto --maxprocesses 4 --dist worksteal tests

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

clean:
	rm -rf $(VENV) runs
