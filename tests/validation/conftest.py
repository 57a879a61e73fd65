"""Fixtures of the validation-study tests: the study's simulated world."""

from __future__ import annotations

import pytest

from drivegain.validation.world import World, make_world


@pytest.fixture(scope="session", autouse=True)
def _single_blas_thread(single_blas_thread: None) -> None:
    """As the study does (see the root conftest)."""


@pytest.fixture(scope="session")
def world() -> World:
    """The study's simulated TX-40 (truth, payloads, shipped excitation, 250 Hz filter)."""
    return make_world()
