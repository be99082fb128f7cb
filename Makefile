# Two commands on a fresh machine: `make demo` (install, train on LASA Sine, write model,
# metrics and plots) and `make test` (install, run the tests). Everything goes into .venv.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# torch is pinned to the CPU build for this project's own install path (constraints.txt);
# the package metadata keeps an open range so it installs anywhere.
PIP_INSTALL := $(BIN)/python -m pip install --quiet -c constraints.txt
# Test processes (pytest-xdist), each running whole test files; 0 runs the suite in this process.
TEST_JOBS ?= 2

.PHONY: install demo test lint format benchmark docs clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PIP_INSTALL) --upgrade pip
	$(PIP_INSTALL) torch==2.13.0
	$(PIP_INSTALL) -e '.[dev,export,cluster,baselines,sim,app,rosbag,lerobot,hdf5,ros,verify]'
	touch $@

demo: install
	$(BIN)/snds train --motion Sine --out runs/Sine --plot

test: install
	$(BIN)/python -m pytest -q -n $(TEST_JOBS) --dist loadfile

lint: install
	$(BIN)/ruff check src tests benchmarks examples
	$(BIN)/ruff format --check src tests benchmarks examples

format: install
	$(BIN)/ruff format src tests benchmarks examples
	$(BIN)/ruff check --fix src tests benchmarks examples

benchmark: install
	$(BIN)/python benchmarks/core.py

# API reference from the docstrings (pdoc, in the dev extra) into site/, git-ignored. Every
# module is named, since snds's __all__ alone would hide the submodules.
docs: install
	$(BIN)/pdoc --docformat google --math -o site snds $$($(BIN)/python -c "import pkgutil, snds; \
	print(' '.join(m.name for m in pkgutil.iter_modules(snds.__path__, 'snds.') \
	if not m.name.startswith(('snds._', 'snds.__'))))")

clean:
	rm -rf $(VENV) runs site
