# Two entry points for a fresh machine (Python 3.11+ and make):
#   make demo   set up .venv and run the whole pipeline on the simulated robot
#   make test   set up .venv-test (a regular, non-editable install) and run ruff, mypy and pytest
PYTHON ?= python3
VENV ?= .venv
TEST_VENV ?= .venv-test

.PHONY: demo test test-load test-vcan bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet -e ".[test,dev]"
	touch $@

demo: $(VENV)/.installed
	$(VENV)/bin/drivegain demo

# The test environment is a regular (non-editable) install: mypy and the packaging test check
# the installed package, not the source folders (see README, "Packaging"). It is created when
# pyproject.toml changes and the package reinstalled (no dependency resolution, seconds) when a
# packaged file changes; a clean checkout, as in CI, builds it from scratch.
PACKAGED := pyproject.toml $(shell find core config dynamics formats excite drivers acquire \
	identify validation fleet -type f ! -path '*/__pycache__/*' 2>/dev/null)

$(TEST_VENV)/.created: pyproject.toml
	rm -rf $(TEST_VENV)
	$(PYTHON) -m venv $(TEST_VENV)
	$(TEST_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(TEST_VENV)/bin/python -m pip install --quiet ".[test,dev]"
	touch $@ $(TEST_VENV)/.installed

$(TEST_VENV)/.installed: $(TEST_VENV)/.created $(PACKAGED)
	$(TEST_VENV)/bin/python -m pip install --quiet --no-deps --force-reinstall .
	touch $@

test: $(TEST_VENV)/.installed
	rm -rf build
	$(TEST_VENV)/bin/ruff check .
	$(TEST_VENV)/bin/ruff format --check .
	cd /tmp && $(CURDIR)/$(TEST_VENV)/bin/mypy --config-file $(CURDIR)/pyproject.toml -p drivegain
	$(TEST_VENV)/bin/python -m pytest -q

# Lockstep on a saturated machine (tests marked `load`): every core busy for minutes, so apart
# from the default suite.
test-load: $(TEST_VENV)/.installed
	$(TEST_VENV)/bin/python -m pytest -q -m load

# The SocketCAN tests (tests/vcan/) on a kernel vcan0 in a QEMU guest: the host kernel has no CAN.
# Installs QEMU, can-utils and a Debian kernel on first use (root or sudo; cached in
# ~/.cache/drivegain-vcan), then boots, runs pytest there and prints vcan0's frame counts.
# Uses .venv-test (after `make test`), else .venv; VCAN_PYTHON=path overrides. See tests/vcan/run -h.
VCAN_PYTHON ?= $(if $(wildcard $(TEST_VENV)/bin/python),$(TEST_VENV),$(VENV))/bin/python
test-vcan:
	tests/vcan/run --python $(VCAN_PYTHON)

# Each benchmark is one command with its own options (--help); this runs them all with their
# defaults, printing ratios to baselines measured in the same run.
bench: $(VENV)/.installed
	for b in regressor identify excite bus acquire; do $(VENV)/bin/python benchmarks/bench_$$b.py || exit 1; done
	$(VENV)/bin/python benchmarks/validate.py --quick --out /tmp/drivegain-validation

clean:
	rm -rf $(VENV) $(TEST_VENV) build *.egg-info drivegain-demo
