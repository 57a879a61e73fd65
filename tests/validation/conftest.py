"""Fixtures of the validation-study tests: the study script as a module, its simulated world."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from drivegain.identify.blas import limited_blas_threads

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "validate.py"


@pytest.fixture(scope="session", autouse=True)
def _single_blas_thread() -> Iterator[None]:
    """As the study does: OpenBLAS threads thrash on the shared, busy cores."""
    with limited_blas_threads(1):
        yield


@pytest.fixture(scope="session")
def validate() -> ModuleType:
    """benchmarks/validate.py, imported (it is a script, not part of the package)."""
    name = "drivegain_validation_study"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses resolve their module through sys.modules
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def world(validate: ModuleType) -> Any:
    """The study's simulated TX-40 (truth, payloads, shipped excitation, 250 Hz filter)."""
    return validate.make_world()
