# Two set-up commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: install demo test lint docs clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# Reinstall whenever the project's requirements change.
$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

demo: install
	$(BIN)/hitl demos --task lift-cube --episodes 3 --out data/demos/demo-lift-cube --seed 0
	$(BIN)/hitl demos --task open-drawer --episodes 3 --out data/demos/demo-open-drawer --seed 0

test: install
	$(BIN)/python -m pytest -q

lint: install
	$(BIN)/ruff check .

# Regenerates the measured expert success table (slow: 50 episodes per task).
docs: install
	$(BIN)/hitl experts --episodes 50 --out docs/experts.md

clean:
	rm -rf $(VENV) .pytest_cache
