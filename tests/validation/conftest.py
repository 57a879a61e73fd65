"""Fixtures of the validation-study tests: the study's simulated world."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from drivegain.identify.blas import limited_blas_threads
from drivegain.validation.world import World, make_world


@pytest.fixture(scope="session", autouse=True)
def _single_blas_thread() -> Iterator[None]:
    """As the study does: OpenBLAS threads thrash on the shared, busy cores."""
    with limited_blas_threads(1):
        yield


@pytest.fixture(scope="session")
def world() -> World:
    """The study's simulated TX-40 (truth, payloads, shipped excitation, 250 Hz filter)."""
    return make_world()
