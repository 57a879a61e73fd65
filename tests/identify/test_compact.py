"""The compact regressor against the dense array it stands for (identify/compact.py)."""

from __future__ import annotations

import numpy as np
import pytest

from drivegain.errors import UsageError
from drivegain.identify.compact import CompactRegressor


@pytest.fixture()
def dense() -> np.ndarray:
    """(N, n, c) with whole zero series in a lower-triangular-like pattern, plus zeros that
    are only zero at some samples (they must be kept)."""
    rng = np.random.default_rng(4)
    w = rng.normal(size=(50, 4, 9))
    for j in range(4):
        w[:, j, : 2 * j] = 0.0  # joint j does not see the first columns
    w[:, 3, 8] = 0.0
    w[::3, 0, 5] = 0.0  # zero at some samples only
    return w


def test_only_series_zero_everywhere_are_dropped(dense: np.ndarray) -> None:
    reg = CompactRegressor.from_dense(dense)
    assert reg.shape == dense.shape
    assert reg.series.shape == (50, 36 - (0 + 2 + 4 + 6) - 1)
    assert (0, 5) in set(zip(reg.joint.tolist(), reg.column.tolist(), strict=True))
    np.testing.assert_array_equal(reg.dense(), dense)


def test_gathers_equal_dense_indexing_bit_for_bit(dense: np.ndarray) -> None:
    reg = CompactRegressor.from_dense(dense)
    idx = np.array([8, 0, 3, 3, 6, 1])  # any order, repeats allowed
    np.testing.assert_array_equal(reg.gather(idx), dense[:, :, idx])
    for j in range(4):
        np.testing.assert_array_equal(reg.joint_columns(j, idx), dense[:, j, idx])
    sl = slice(7, 31)
    part = reg.rows(sl)
    assert np.shares_memory(part.series, reg.series)
    np.testing.assert_array_equal(part.gather(idx), dense[sl][:, :, idx])


def test_dot_is_the_dense_product(dense: np.ndarray) -> None:
    reg = CompactRegressor.from_dense(dense)
    coef = np.random.default_rng(5).normal(size=9)
    np.testing.assert_allclose(reg.dot(coef), dense @ coef, rtol=1e-14, atol=1e-14)
    # several coefficient vectors at once: (N, n, K)
    many = np.random.default_rng(6).normal(size=(9, 3))
    np.testing.assert_allclose(reg.dot(many), dense @ many, rtol=1e-14, atol=1e-14)


def test_wrong_shape_is_refused() -> None:
    with pytest.raises(UsageError, match=r"\(samples, joints, columns\)"):
        CompactRegressor.from_dense(np.zeros((10, 6)))
