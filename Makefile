# Two entry points for a fresh machine (Python 3.11+ and make):
#   make demo   set up .venv and run the whole pipeline on the simulated robot
#   make test   set up .venv-test (a regular, non-editable install) and run ruff, mypy and pytest
PYTHON ?= python3
VENV ?= .venv
TEST_VENV ?= .venv-test

.PHONY: demo test bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet -e ".[test,dev]"
	touch $@

demo: $(VENV)/.installed
	$(VENV)/bin/drivegain demo

# The test environment is rebuilt from the working tree each run: mypy and the packaging test
# check the installed package, not the source folders (see README, "Packaging").
test:
	rm -rf $(TEST_VENV)
	$(PYTHON) -m venv $(TEST_VENV)
	$(TEST_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(TEST_VENV)/bin/python -m pip install --quiet ".[test,dev]"
	rm -rf build
	$(TEST_VENV)/bin/ruff check .
	$(TEST_VENV)/bin/ruff format --check .
	cd /tmp && $(CURDIR)/$(TEST_VENV)/bin/mypy --config-file $(CURDIR)/pyproject.toml -p drivegain
	$(TEST_VENV)/bin/python -m pytest -q

# Each benchmark is one command with its own options (--help); this runs them all with their
# defaults, printing ratios to baselines measured in the same run.
bench: $(VENV)/.installed
	for b in regressor identify excite bus acquire; do $(VENV)/bin/python benchmarks/bench_$$b.py || exit 1; done
	$(VENV)/bin/python benchmarks/validate.py --quick --out /tmp/drivegain-validation

clean:
	rm -rf $(VENV) $(TEST_VENV) build *.egg-info drivegain-demo
