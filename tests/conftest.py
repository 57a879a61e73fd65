"""Fixtures shared by all test folders."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """``../shared`` beside the checkout (exists in CI, not in a user's clone)."""
    if not SHARED.is_dir():
        pytest.skip("../shared (real TX-40 data, docs) is not beside this checkout")
    return SHARED


@pytest.fixture(scope="session")
def tx40_real(shared_dir: Path) -> Path:
    d = shared_dir / "data" / "tx40-real"
    if not (d / "pos_read_data.csv").is_file():
        pytest.skip("../shared/data/tx40-real is missing")
    return d
