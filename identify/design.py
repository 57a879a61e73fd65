"""Designs: one prepared run seen through one friction form's base parameters.

A :class:`Design` holds, per joint j, the rows ``D_j = [W_base | W_payload | V_j]`` of one run
(Gautier & Briot 2012, eq. 19-21). Every estimator of the procedure works on the per-joint R
factors of those rows and a *column transform* T, so that ``D_j T`` holds the unknowns of its
problem (:func:`ls_transform` for IDIM-(W)LS with known gains, :func:`tls_transform` for
IDIM-WTLS): the α grid and the σ iteration then cost almost nothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivegain.config.payload import PAYLOAD_PARAMS
from drivegain.config.robot import Robot, WristFriction
from drivegain.dynamics.base import BaseParameters
from drivegain.identify.columns import base_keys, payload_keys
from drivegain.identify.estimate import r_factor
from drivegain.identify.hac import phase_bins
from drivegain.identify.prepare import PreparedRun

#: Samples per row block of :meth:`Design.factors`.
FACTOR_BLOCK = 4096


@dataclass(frozen=True)
class Design:
    """Rows of one run: per joint j, ``D_j = [W_base | W_payload | V_j]`` (N, nb + 10 + n).

    ``W_payload`` holds the inertial columns of the payload's link (zero for an unloaded run);
    ``V_j`` is row j of the coupled current matrix (eq. 21).

    ``row_weight`` (N, n), when given, multiplies row k of ``D_j`` by its entry (k, j) in every
    product of the rows (:meth:`block`, :meth:`factors`, :meth:`dot`, :meth:`tdot`): 0 leaves
    an entry out of a fit (:func:`without_rows`). The torques :meth:`torque` and
    :meth:`model_torque` are the run's own, unweighted.
    """

    run: PreparedRun
    base_idx: np.ndarray
    payload_idx: np.ndarray | None
    kt: np.ndarray
    row_weight: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.kt.shape[0])

    @property
    def nb(self) -> int:
        return int(self.base_idx.shape[0])

    @property
    def m(self) -> int:
        return self.nb + len(PAYLOAD_PARAMS) + self.n

    @property
    def rows(self) -> int:
        return self.run.samples

    @property
    def loaded(self) -> bool:
        return self.payload_idx is not None

    def block(self, j: int) -> np.ndarray:
        """``D_j`` (N, m)."""
        w = self.run.regressor
        out = np.zeros((self.rows, self.m))
        out[:, : self.nb] = w.joint_columns(j, self.base_idx)
        if self.payload_idx is not None:
            out[:, self.nb : self.nb + 10] = w.joint_columns(j, self.payload_idx)
        out[:, self.nb + 10 :] = self.run.current * self.kt[j][None, :]
        if self.row_weight is not None:
            out *= self.row_weight[:, j, None]
        return out

    def entries(self, j: int) -> int:
        """Rows of ``D_j`` that count (every row unless :attr:`row_weight` zeroes some)."""
        if self.row_weight is None:
            return self.rows
        return int(np.count_nonzero(self.row_weight[:, j]))

    def factors(self, joints: Sequence[int] | None = None) -> np.ndarray:
        """R factors of every joint's ``D_j``: (n, m, m), ``R_jᵀR_j = D_jᵀD_j``.

        ``joints``: only those joints' factors (the others are left zero; None: all).

        Only the columns of ``D_j`` that are not zero by construction enter the QR (joint j's
        own regressor series, and the currents its row of kt couples): a joint's row misses
        the links before it and the other joints' friction, an unloaded run has no payload
        columns, and kt is nearly diagonal, so about half of the columns are zero and the QR
        (quadratic in the columns) costs a third. The zero columns of ``D_j`` are zero
        columns of R_j, so ``R_jᵀR_j = D_jᵀD_j`` as with the whole block.
        """
        out = np.zeros((self.n, self.m, self.m))
        for j in range(self.n) if joints is None else joints:
            cols, series, coupled = self._nonzero_columns(j)
            scale = self.kt[j, coupled][None, :]
            # Row blocks reduced in turn with the R so far: a tall-skinny QR runs about twice
            # as fast on blocks that stay in cache as on the whole run.
            r = np.zeros((cols.size, cols.size))
            for k in range(0, self.rows, FACTOR_BLOCK):
                rows = slice(k, k + FACTOR_BLOCK)
                block = np.hstack(
                    [
                        self.run.regressor.series[rows, series],
                        self.run.current[rows, coupled] * scale,
                    ]
                )
                if self.row_weight is not None:
                    block *= self.row_weight[rows, j, None]
                r = r_factor(np.vstack([r, block]))
            # cols ascend, so R of the kept columns placed in their rows 0..k-1 is triangular
            rj = out[j]
            rj[: cols.size, cols] = r
        return out

    def same_rows(self, other: Design, j: int) -> bool:
        """Whether joint j's rows ``D_j`` are those of ``other`` (the same run, columns and
        coupling), so that their factors are the same numbers: two friction forms' designs
        differ only in the joints a coupled motor's Coulomb column reaches."""
        if self.run is not other.run or self.m != other.m or not np.array_equal(self.kt, other.kt):
            return False
        if self.row_weight is not other.row_weight:
            return False
        mine, theirs = self._nonzero_columns(j), other._nonzero_columns(j)
        return all(np.array_equal(x, y) for x, y in zip(mine, theirs, strict=True))

    def _nonzero_columns(self, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The columns of ``D_j`` that may be non-zero (ascending), the regressor series of
        the first ones and the currents of the last ones (every other column is zero)."""
        reg = self.run.regressor
        jj, pp, ss = reg.entries(self.base_idx)
        cols = [pp[jj == j]]
        series = [ss[jj == j]]
        if self.payload_idx is not None:
            jj, pp, ss = reg.entries(self.payload_idx)
            cols.append(self.nb + pp[jj == j])
            series.append(ss[jj == j])
        coupled = np.flatnonzero(self.kt[j] != 0.0)
        idx = np.concatenate([*cols, self.nb + 10 + coupled]).astype(np.intp)
        return idx, np.concatenate(series).astype(np.intp), coupled

    def torque(self, gains: np.ndarray) -> np.ndarray:
        """Joint torques V·g (N·m) the current references stand for with ``gains``, (N, n)."""
        return self.run.current @ (self.kt * np.asarray(gains)[None, :]).T

    def model_torque(self, chi: np.ndarray, chi_payload: np.ndarray | None) -> np.ndarray:
        """Joint torques W·χ + W_L·χ_L of the model (N·m), (N, n)."""
        coef = np.zeros(self.run.regressor.c)
        np.add.at(coef, self.base_idx, chi)
        if self.payload_idx is not None and chi_payload is not None:
            np.add.at(coef, self.payload_idx, chi_payload)
        return self.run.regressor.dot(coef)

    def dot(self, coef: np.ndarray) -> np.ndarray:
        """``D_j c`` for every joint j at once, (N, n), for coefficients c (m,) of the columns
        of ``D_j`` (units: those of ``D_j`` times c's), without building any ``D_j``."""
        nb = self.nb
        coef = np.asarray(coef, dtype=float)
        dense = np.zeros(self.run.regressor.c)
        # add.at: a column of the payload's link may also be a base column
        np.add.at(dense, self.base_idx, coef[:nb])
        if self.payload_idx is not None:
            np.add.at(dense, self.payload_idx, coef[nb : nb + 10])
        v_part = self.run.current @ (self.kt * coef[nb + 10 :][None, :]).T
        out = self.run.regressor.dot(dense) + v_part
        if self.row_weight is not None:
            out *= self.row_weight
        return np.asarray(out)

    def tdot(self, weights: np.ndarray) -> np.ndarray:
        """``Σ_j w_kj D_j,k`` for every sample k, (N, m), for per-sample joint weights
        ``weights`` w (N, n): the transpose of :meth:`dot`, sample by sample."""
        w = np.asarray(weights, dtype=float)
        if self.row_weight is not None:
            w = w * self.row_weight
        reg = self.run.regressor
        # Each regressor series (joint j, column c) adds w_kj times itself to the columns of
        # D that stand for c: one product with that 0/1 (series, m) map.
        where = np.zeros((reg.joint.size, self.m))
        groups = [(0, self.base_idx)]
        if self.payload_idx is not None:
            groups.append((self.nb, self.payload_idx))
        for offset, idx in groups:
            _, pp, ss = reg.entries(idx)
            where[ss, offset + pp] = 1.0
        out = (reg.series * w[:, reg.joint]) @ where
        out[:, self.nb + 10 :] = self.run.current * (w @ self.kt)
        return np.asarray(out)

    def subset(self, sl: slice) -> Design:
        weight = None if self.row_weight is None else self.row_weight[sl]
        return Design(self.run.rows(sl), self.base_idx, self.payload_idx, self.kt, weight)


def run_phases(d: Design) -> tuple[np.ndarray, int] | None:
    """:func:`~drivegain.identify.hac.phase_bins` of the design's run."""
    r = d.run
    return phase_bins(r.t, r.period_s, r.rate_hz, r.phase_origin_s)


def same_phases(designs: Sequence[Design]) -> bool:
    """Whether the runs' phases are of one excitation and comparable: each run knows when the
    excitation started, and all have the same period."""
    runs = [d.run for d in designs]
    return all(r.phase_origin_s is not None for r in runs) and (
        runs[0].period_s is not None and all(r.period_s == runs[0].period_s for r in runs)
    )


def coupling_factor(robot: Robot) -> np.ndarray:
    """kt with ``V[:, j, :] = v * kt[j]`` (eq. 21): 1 on the diagonal and at coupled motors."""
    k = robot.transmission()
    return np.asarray(k.T / np.diag(k)[None, :])


def make_design(run: PreparedRun, bp: BaseParameters, form: WristFriction, robot: Robot) -> Design:
    """The design of ``run`` for the base parameters ``bp`` of friction form ``form``."""
    base_idx = run.column_index(base_keys(bp, form))
    payload_idx = None
    if run.payload is not None:
        payload_idx = run.column_index(payload_keys(robot, run.payload.link))
    return Design(run=run, base_idx=base_idx, payload_idx=payload_idx, kt=coupling_factor(robot))


# --------------------------------------------------------------------------------------------
# Column transforms: the unknowns of each problem as combinations of a design's columns


def ls_transform(d: Design, slot: int | None, n_slots: int, gains: np.ndarray) -> np.ndarray:
    """Column transform of IDIM-(W)LS with known gains: ``D T = [W_base | W_payload | V g]``.

    Parameters
    ----------
    d
        The design.
    slot
        Index of this run's payload among the ``n_slots`` payloads solved together, or None for
        an unloaded run.
    n_slots
        Number of payloads solved together (10 unknowns each).
    gains
        Drive gains, N·m/A, (n,).

    Returns
    -------
    numpy.ndarray
        T, (m, nb + 10·n_slots + 1); its last column gives the measured torque V g.
    """
    nb, m = d.nb, d.m
    k = nb + 10 * n_slots
    t = np.zeros((m, k + 1))
    t[:nb, :nb] = np.eye(nb)
    if slot is not None:
        t[nb : nb + 10, nb + 10 * slot : nb + 10 * (slot + 1)] = np.eye(10)
    t[nb + 10 :, k] = gains
    return t


def tls_transform(
    d: Design, known: np.ndarray, chi_known: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """Column transform of IDIM-WTLS: ``D T = [−W, V·diag(w), −W_uL, −W_kL χ_kL]`` (eq. 19).

    Parameters
    ----------
    d
        The design; the payload columns (−W_uL, −W_kL χ_kL) are filled only if it is loaded.
    known
        Mask over the 10 payload parameters of those whose value is known, (10,).
    chi_known
        Values of the known payload parameters (SI units), (count of ``known``,).
    weights
        Per-drive weights w = α·c of the V columns
        (:func:`drivegain.identify.weighting.drive_noise_weights`), scalar or (n,).

    Returns
    -------
    numpy.ndarray
        T, (m, nb + n + unknown payload parameters + 1); its last column is δ's.
    """
    nb, n, m = d.nb, d.n, d.m
    unknown = np.flatnonzero(~known)
    nu = unknown.size
    t = np.zeros((m, nb + n + nu + 1))
    t[:nb, :nb] = -np.eye(nb)
    t[nb + 10 :, nb : nb + n] = np.diag(np.broadcast_to(weights, (n,)))
    if d.loaded:
        for col, p in enumerate(unknown):
            t[nb + p, nb + n + col] = -1.0
        t[nb + np.flatnonzero(known), -1] = -chi_known
    return t


def stacked_factor(
    factors: Sequence[np.ndarray], transforms: Sequence[np.ndarray], weights: np.ndarray
) -> np.ndarray:
    """R factor of the stacked, row-weighted, column-transformed rows of several runs.

    Parameters
    ----------
    factors
        Per run, the R factors of every joint's rows, (n, m, m).
    transforms
        Per run, the column transform T of the problem.
    weights
        Row weight of each joint, 1/σ_j (1/(N·m)), (n,).

    Returns
    -------
    numpy.ndarray
        Upper-triangular R of ``[w_j R_j T]`` over runs and joints.
    """
    blocks = [
        weights[j] * (f[j] @ t)
        for f, t in zip(factors, transforms, strict=True)
        for j in range(f.shape[0])
    ]
    return r_factor(np.vstack(blocks))


def joint_residual_sq(
    factors: Sequence[np.ndarray], transforms: Sequence[np.ndarray], x_aug: np.ndarray
) -> np.ndarray:
    """Σ over runs of ‖D_j T x‖² per joint.

    Parameters
    ----------
    factors, transforms
        As for :func:`stacked_factor`.
    x_aug
        Unknowns with the fixed last component appended (−1 for a residual, as in ``[x; −1]``).

    Returns
    -------
    numpy.ndarray
        Squared norm of the unweighted equation errors of each joint, (N·m)², (n,).
    """
    n = factors[0].shape[0]
    out = np.zeros(n)
    for f, t in zip(factors, transforms, strict=True):
        tx = t @ x_aug
        out += np.array([float(np.sum((f[j] @ tx) ** 2)) for j in range(n)])
    return out
