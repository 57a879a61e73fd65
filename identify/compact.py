"""A run's regressor without the entries that are zero at every sample.

Joint j's torque does not depend on the links before it, nor on another joint's friction, so
about half of the (joint, column) entries of the IDIM regressor are zero at every sample
(182 of 384 for the TX-40's stored columns). :class:`CompactRegressor` keeps only the other
series; the estimators gather the columns they need from it a row block at a time. A gathered
block equals the same block of the dense regressor bit for bit (the dropped entries are 0.0),
so no result depends on which form is stored, and a long run's regressor takes half the memory.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from drivegain.errors import UsageError

__all__ = ["CompactRegressor"]


@dataclass(frozen=True)
class CompactRegressor:
    """The non-zero series of a regressor of shape (N, n, c).

    Attributes
    ----------
    series
        The kept series, joint torque (N·m) per parameter unit, (N, k).
    joint, column
        Joint row and regressor column of each series, (k,) each, in C order of (joint, column).
    n, c
        Joints and regressor columns of the dense regressor.
    """

    series: np.ndarray
    joint: np.ndarray
    column: np.ndarray
    n: int
    c: int

    @classmethod
    def from_dense(cls, w: np.ndarray) -> CompactRegressor:
        """Keep the (joint, column) series of ``w`` (N, n, c) that are not zero everywhere."""
        w = np.asarray(w, dtype=float)
        if w.ndim != 3:
            raise UsageError(f"a regressor has shape (samples, joints, columns), not {w.shape}")
        joint, column = np.nonzero(np.any(w != 0.0, axis=0))
        return cls(np.ascontiguousarray(w[:, joint, column]), joint, column, w.shape[1], w.shape[2])

    @property
    def shape(self) -> tuple[int, int, int]:
        """Shape of the dense regressor, (N, n, c)."""
        return (int(self.series.shape[0]), self.n, self.c)

    @property
    def samples(self) -> int:
        return int(self.series.shape[0])

    def rows(self, sl: slice) -> CompactRegressor:
        """The samples ``sl`` (a view, no copy)."""
        return replace(self, series=self.series[sl])

    def entries(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The kept entries among the columns ``idx``: their joints, their positions in ``idx``
        and their series (indices into :attr:`series`), three (m,) arrays in C order of
        (joint, position)."""
        where = np.full((self.n, self.c), -1, dtype=np.intp)
        where[self.joint, self.column] = np.arange(self.joint.size)
        sel = where[:, np.asarray(idx, dtype=np.intp)]
        jj, pp = np.nonzero(sel >= 0)
        return jj, pp, sel[jj, pp]

    def gather(self, idx: np.ndarray) -> np.ndarray:
        """``dense[:, :, idx]``, (N, n, len(idx)) (a new array)."""
        idx = np.asarray(idx, dtype=np.intp)
        jj, pp, ss = self.entries(idx)
        out = np.zeros((self.samples, self.n, idx.size))
        out[:, jj, pp] = self.series[:, ss]
        return out

    def joint_columns(self, j: int, idx: np.ndarray) -> np.ndarray:
        """``dense[:, j, idx]``, (N, len(idx)) (a new array)."""
        idx = np.asarray(idx, dtype=np.intp)
        jj, pp, ss = self.entries(idx)
        mine = jj == j
        out = np.zeros((self.samples, idx.size))
        out[:, pp[mine]] = self.series[:, ss[mine]]
        return out

    def dot(self, coef: np.ndarray) -> np.ndarray:
        """``dense @ coef`` for ``coef`` (c,): the torque of each joint, (N, n); for ``coef``
        (c, K), K such sums at once, (N, n, K)."""
        coef = np.asarray(coef, dtype=float)
        k = self.joint.size
        # One product with a (k, n·K) matrix holding each series' coefficients in its joint's
        # columns: a single pass over the series (gathering each joint's takes three times as
        # long); the zeros add nothing.
        by_joint = np.zeros((k, self.n, *coef.shape[1:]))
        by_joint[np.arange(k), self.joint] = coef[self.column]
        out = self.series @ by_joint.reshape(k, -1)
        return np.asarray(out.reshape(-1, self.n, *coef.shape[1:]))

    def dense(self) -> np.ndarray:
        """The dense regressor, (N, n, c) (for tests and small runs)."""
        out = np.zeros(self.shape)
        out[:, self.joint, self.column] = self.series
        return out
