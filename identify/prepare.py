"""From sampled runs to the decimated observation data the estimators use (paper §2.2).

For each run: filtered positions, velocities and accelerations (zero-phase Butterworth + central
differences, :mod:`drivegain.identify.signal`), the IDIM regressor at the full rate, then the
parallel decimation of the regressor columns and the current references with the same filter,
border trimming. Only the regressor columns some estimator needs are kept: the base columns of
both coupled-wrist friction forms and the inertial columns of the payload's link.

The full-rate regressor is built and decimated in chunks of samples that overlap by more than
the decimation filter's memory, so memory stays bounded by the decimated data (linear in the
recording's length, with a small constant) whatever the recording's length.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from drivegain.config.payload import Payload
from drivegain.dynamics.base import random_states
from drivegain.dynamics.model import RobotModel
from drivegain.errors import DataError
from drivegain.identify.columns import regressor_columns
from drivegain.identify.compact import CompactRegressor
from drivegain.identify.coulombsign import encoder_steps, sign_cutoff
from drivegain.identify.decimate import (
    decimate_columns,
    decimation_memory,
    decimation_windows,
    first_equal,
    parallel_decimate,
)
from drivegain.identify.reversals import (
    coulomb_sources,
    masked_drives,
    reversal_entries,
    reversal_marks,
    reversal_mask,
)
from drivegain.identify.signal import FilterSettings, derivatives

#: Full-rate samples per regressor evaluation and least decimation chunk: the (chunk, n, 86)
#: temporary is ~17 MB for n = 6.
CHUNK = 4096
#: Decimation windows span at least this many filter memories: each is filtered with a memory
#: on either side that its neighbours filter too, so 1/8 of the samples is filtered twice...
WINDOW_PADS = 16
#: ... unless a window's regressor series would take more bytes than this (at 5 kHz a memory is
#: 5 560 samples); windows of two memories are the least.
WINDOW_BYTES = 32 * 2**20

#: Called with the number of full-rate samples just processed (progress display).
Progress = Callable[[int], None]


@dataclass(frozen=True)
class PreparedRun:
    """One run reduced to what the estimators need (decimated, borders trimmed).

    Attributes
    ----------
    label
        Run label (``unloaded``, ``loaded``, ``validation`` or the log's own).
    t
        Time of each kept sample, s, (N,).
    regressor
        Regressor columns, (N, n, c), joint torque (N·m) per parameter unit, without the
        entries that are zero at every sample.
    columns
        Keys of the regressor columns (standard names; ``fcm6@paper`` for the other form).
    current
        Current references, A (or the log's unit), (N, n).
    rate_hz
        Sample rate of the kept samples, Hz.
    payload
        Payload fixed to the robot during the run, or None.
    filter
        Filter settings used (None: exact derivatives were given).
    source
        Where the data came from (file name), for messages.
    raw_samples
        Samples of the recording before filtering and decimation.
    period_s
        Period of the excitation when it is periodic (errors that depend on the pose repeat
        with it), else None.
    phase_origin_s
        When the excitation started on the clock of ``t`` (its phase 0), s, if known: runs of
        one excitation then have comparable phases (:func:`~drivegain.identify.hac.phase_bins`).
    rest_samples
        Samples of the recording where the robot was at rest (:func:`at_rest`); decimated
        samples near them are not kept, so ``t`` may have gaps.
    reversal_share
        Per kept sample and drive, the share of the decimation filter's window near a reversal
        of a Coulomb velocity of that drive (:mod:`~drivegain.identify.reversals`), (N, n);
        None when not computed (exact derivatives).
    reversal_coulomb
        The columns of :attr:`regressor`, after those of :attr:`columns`, of the Coulomb
        velocities' signs inside their reversal zones, one per velocity of
        :func:`~drivegain.identify.reversals.coulomb_sources` that has one
        (:func:`~drivegain.identify.reversals.reversal_marks`); None when not computed. Only the
        maximum-likelihood gains use them.
    """

    label: str
    t: np.ndarray
    regressor: CompactRegressor
    columns: tuple[str, ...]
    current: np.ndarray
    rate_hz: float
    payload: Payload | None
    filter: FilterSettings | None
    source: str
    raw_samples: int
    period_s: float | None = None
    rest_samples: int = 0
    reversal_share: np.ndarray | None = None
    reversal_coulomb: np.ndarray | None = None
    phase_origin_s: float | None = None

    @property
    def samples(self) -> int:
        return int(self.t.shape[0])

    def column_index(self, keys: Sequence[str]) -> np.ndarray:
        """Positions of ``keys`` in :attr:`regressor`'s last axis."""
        pos = {k: i for i, k in enumerate(self.columns)}
        return np.array([pos[k] for k in keys], dtype=int)

    def rows(self, sl: slice) -> PreparedRun:
        """The same run restricted to the samples ``sl`` (views, no copy)."""
        return PreparedRun(
            label=self.label,
            t=self.t[sl],
            regressor=self.regressor.rows(sl),
            columns=self.columns,
            current=self.current[sl],
            rate_hz=self.rate_hz,
            payload=self.payload,
            filter=self.filter,
            source=self.source,
            raw_samples=self.raw_samples,
            period_s=self.period_s,
            rest_samples=self.rest_samples,
            reversal_share=None if self.reversal_share is None else self.reversal_share[sl],
            reversal_coulomb=self.reversal_coulomb,
            phase_origin_s=self.phase_origin_s,
        )


def prepare_exact(
    model: RobotModel,
    columns: Sequence[str],
    *,
    label: str,
    t: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    current: np.ndarray,
    payload: Payload | None = None,
    source: str = "",
    period_s: float | None = None,
) -> PreparedRun:
    """A run whose velocities and accelerations are known exactly: no filter, no decimation."""
    t = np.asarray(t, dtype=float)
    w = np.concatenate(
        [
            regressor_columns(
                model, q[s : s + CHUNK], qd[s : s + CHUNK], qdd[s : s + CHUNK], columns
            )
            for s in range(0, len(t), CHUNK)
        ]
    )
    rate = 1.0 / float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    return PreparedRun(
        label=label,
        t=t,
        regressor=CompactRegressor.from_dense(w),
        columns=tuple(columns),
        current=np.asarray(current, dtype=float),
        rate_hz=rate,
        payload=payload,
        filter=None,
        source=source,
        raw_samples=len(t),
        period_s=period_s,
    )


def filtered_derivatives(
    q: np.ndarray, rate_hz: float, settings: FilterSettings, *, source: str | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions low-passed by :func:`signal.derivatives`, then five-point central differences.

    The three-point differences (q[k+1] − q[k−1])/2h and (q[k+1] − 2q[k] + q[k−1])/h² shrink a
    harmonic of angular frequency ω by (ωh)²/6 and (ωh)²/12: 5e-5 on q̈ for 1 Hz sampled at
    250 Hz. Small, but it is systematic, the same on every run, and was measured to bias the
    IDIM-WTLS gains by about one standard deviation with two 60 s runs (the bias does not
    shrink with more data, the standard deviation does). The five-point stencils leave
    (ωh)⁴/30 and (ωh)⁴/90. The two samples at each end, where the stencils do not fit, repeat
    their neighbours; they lie in the border that decimation trims.
    """
    qf, _, _ = derivatives(q, rate_hz, settings, source=source)
    qd, qdd = np.empty_like(qf), np.empty_like(qf)
    for s in range(0, qf.shape[0], CHUNK):
        qd[s : s + CHUNK], qdd[s : s + CHUNK] = five_point(qf, rate_hz, s, s + CHUNK)
    return qf, qd, qdd


def five_point(
    qf: np.ndarray, rate_hz: float, start: int, stop: int
) -> tuple[np.ndarray, np.ndarray]:
    """The five-point velocity and acceleration (rad/s, rad/s²) of samples ``start:stop`` of the
    filtered positions ``qf`` (:func:`filtered_derivatives`; ``stop`` is clipped to the run).

    A window of a long run needs no velocity and acceleration of the whole run in memory.
    """
    n = qf.shape[0]
    k = np.clip(np.arange(start, min(stop, n)), 2, n - 3)  # the ends repeat their neighbours
    h = 1.0 / rate_hz
    a, b, c, d, e = qf[k - 2], qf[k - 1], qf[k], qf[k + 1], qf[k + 2]
    qd = (a - 8.0 * b + 8.0 * d - e) / (12.0 * h)
    qdd = (-a + 16.0 * b - 30.0 * c + 16.0 * d - e) / (12.0 * h * h)
    return qd, qdd


#: A joint slower than this fraction of its RMS speed counts as still (for :func:`at_rest`).
REST_FRACTION = 0.01
#: Decimated samples whose filter window holds more than this fraction of rest are dropped
#: (measured on the real TX-40 recording, whose trajectory also stops for 15-20 ms every 0.6 s:
#: 1e-3 keeps 42 % of the samples, relative residual 0.056; 1e-2 keeps 70 %, 0.060; no
#: exclusion 0.114, with the Coulomb coefficients pulled 30-40 % low).
REST_LEAK = 1e-2


def at_rest(qd: np.ndarray) -> np.ndarray:
    """Samples where every joint is (nearly) still: (N,) bool.

    At rest the Coulomb terms sign(q̇) follow the noise of the filtered velocity and the
    torque holds the robot anywhere within the static friction band: the IDIM does not apply.
    Recordings usually begin and end at rest (the real TX-40 one: its last 1.5 s), and those
    samples, left in, changed the fit with velocity round-off. While the robot moves, one
    joint reversing is fine: its sign changes at a well-defined instant.
    """
    speed = np.abs(np.asarray(qd, dtype=float))
    rms = np.sqrt(np.mean(speed**2, axis=0))
    still = speed <= REST_FRACTION * np.where(rms > 0, rms, np.inf)
    return np.asarray(np.all(still, axis=1))


def _random_regressor(model: RobotModel, columns: Sequence[str]) -> np.ndarray:
    """The regressor ``columns`` at 20 random states, (20, n, c): which entries are not
    identically zero (joint rows do not depend on the links before them), which repeat."""
    rng = np.random.default_rng(0)
    q, qd, qdd = random_states(model, 20, rng)
    return regressor_columns(model, q, qd, qdd, columns)


def aligned_current(current: np.ndarray, delay: float) -> np.ndarray:
    """Currents interpolated onto the position samples: ``c[k] ← (1−d)·c[k] + d·c[k+1]``.

    Sample k of a current ``delay`` samples old stands for t_k − d·T; between it and sample
    k+1 (t_k + (1−d)·T) the value at t_k is the linear interpolation. The last sample is kept
    (it falls in the trimmed border). ``delay`` 0 returns ``current`` itself.
    """
    if delay == 0.0 or current.shape[0] < 2:
        return current
    out = current.copy()
    out[:-1] = (1.0 - delay) * current[:-1] + delay * current[1:]
    return out


def prepare_recording(
    model: RobotModel,
    columns: Sequence[str],
    *,
    label: str,
    q: np.ndarray,
    current: np.ndarray,
    rate_hz: float,
    settings: FilterSettings,
    payload: Payload | None = None,
    source: str = "",
    t0: float = 0.0,
    progress: Progress | None = None,
    period_s: float | None = None,
) -> PreparedRun:
    """Filter, differentiate, build the regressor and decimate one recorded run.

    The full-rate regressor exists only for a window of samples at a time: each chunk is
    decimated with the samples around it that the decimation filter remembers
    (:func:`~.decimate.decimation_memory`), which the next chunk reuses rather than recomputes,
    so the result equals a whole-signal decimation and memory stays bounded by the decimated
    output.
    Structurally zero regressor entries are not filtered.

    Parameters
    ----------
    model
        The robot model.
    columns
        Regressor columns to keep (:func:`stored_columns`).
    label
        Run label.
    q
        Measured joint positions, rad, (N, n), uniformly sampled.
    current
        Current references, (N, n).
    rate_hz
        Sample rate, Hz.
    settings
        Filter and decimation settings.
    payload
        Payload of this run, if any.
    source
        File name for error messages.
    t0
        Time of the first sample, s.
    progress
        Called with the number of samples processed.
    period_s
        Period of the excitation, if periodic.

    Raises
    ------
    DataError
        Too few samples for the filters, NaN/inf.
    """
    q = np.asarray(q, dtype=float)
    current = aligned_current(np.asarray(current, dtype=float), settings.current_delay)
    n_samples, n = q.shape
    src = source or None
    # Velocities and accelerations exist for a window at a time (five_point), except the
    # velocity of the whole run for a moment, to find the samples at rest and the Coulomb
    # sign's cut-off (its drives' RMS speeds).
    qf = derivatives(q, rate_hz, settings, source=src)[0]
    qd = np.empty_like(qf)
    for s in range(0, n_samples, CHUNK):
        qd[s : s + CHUNK] = five_point(qf, rate_hz, s, s + CHUNK)[0]
    settings = _with_sign_cutoff(model, q, qd, rate_hz, settings)
    # Positions for the Coulomb columns' signs, when their cut-off differs (FilterSettings).
    qs = None
    if settings.sign_cutoff != settings.cutoff_hz:
        for_sign = replace(settings, cutoff_hz=settings.sign_cutoff)
        qs = derivatives(q, rate_hz, for_sign, source=src)[0]
    f = settings.decimate
    pad = decimation_memory(f)
    at_random = _random_regressor(model, columns)
    rows, cols = np.nonzero(np.any(at_random != 0.0, axis=0))
    # series equal at random states: each group is filtered once if equal in a window too.
    # A window holds the series to filter first, their repeats last (decimate_columns takes
    # the first ones as slices): its column i is series order[i].
    same_as = first_equal(at_random[:, rows, cols])
    order = np.argsort(same_as != np.arange(rows.size), kind="stable")
    place = np.argsort(order)
    same_in_window = place[same_as[order]]
    cap = WINDOW_BYTES // (8 * max(1, rows.size)) - 2 * pad
    size = max(CHUNK, 2 * pad, min(WINDOW_PADS * pad, cap))
    parts = [(0, n_samples)]
    if n_samples > size + 2 * pad:
        parts = decimation_windows(n_samples, f, size)
    # Decimate the currents once, whole: they are small. Same filter, so the same result.
    # The rest indicator goes through the same filter: a kept sample's filter window holds
    # (almost) no sample at rest.
    rest = at_rest(qd)
    zones, signs = reversal_marks(qd, model.robot)
    del qd
    mask = None
    if settings.reversal_mask_s is not None:
        # Both sides of every equation weighted alike before the decimation, so Y = W χ stays
        # exact without the stretches around reversals (reversals.reversal_mask). The mask is
        # 0 wherever a zone reaches its group, so no entry of a masked group keeps a share near
        # a reversal, and no reversal Coulomb column of its velocities is left to fit.
        drives = settings.reversal_mask_drives
        mask = reversal_mask(zones, model.robot, rate_hz, settings.reversal_mask_s, drives)
        current = current * mask
        masked = masked_drives(model.robot, drives)
        zones = np.where(masked[None, :], 0.0, zones)
        # a velocity's reversal Coulomb column goes with the groups it reaches: gone when all
        # of them are masked (where they are not, its share and column stay)
        source_reach = coulomb_sources(model.robot)[1]
        gone = ~np.any(source_reach & ~masked[None, :], axis=1)
        signs = np.where(gone[None, :], 0.0, signs)
    (c_all, rest_d, zones_d, signs_d) = parallel_decimate(
        [current, rest.astype(float), zones, signs], f, 0, source=src
    )
    nd = c_all.shape[0]
    # the reversal Coulomb series follow the regressor's, as columns after len(columns)
    s_joint, s_source, s_weight = reversal_entries(model.robot)
    used = np.any(signs != 0.0, axis=0)
    del signs
    mine = used[s_source]
    s_joint, s_source, s_weight = s_joint[mine], s_source[mine], s_weight[mine]
    w_all = np.zeros((nd, rows.size + s_joint.size))  # the series not zero everywhere
    w_all[:, rows.size :] = signs_d[:, s_source] * s_weight
    carry: np.ndarray | None = None  # regressor series of the previous window's tail
    carry_lo = 0
    for a, b in parts:
        lo, hi = max(0, a - pad), min(n_samples, b + pad)
        # column-major: each series' samples contiguous, as the decimation filters them
        window = np.empty((hi - lo, rows.size), order="F")
        start = lo
        if carry is not None and carry_lo == lo:
            window[: carry.shape[0]] = carry
            start = lo + carry.shape[0]
        for s in range(start, hi, CHUNK):
            e = min(hi, s + CHUNK)
            sign_qd = None if qs is None else five_point(qs, rate_hz, s, e)[0]
            window[s - lo : e - lo] = regressor_columns(
                model,
                qf[s:e],
                *five_point(qf, rate_hz, s, e),
                columns,
                (rows[order], cols[order]),
                sign_qd=sign_qd,
            )
            if mask is not None:  # series i belongs to joint rows[order[i]]
                window[s - lo : e - lo] *= mask[s:e][:, rows[order]]
        # Decimated sample k of this window is input sample lo + k·f (lo is a multiple of f).
        first = (a - lo) // f
        count = -(-(b - a) // f)
        k0 = a // f
        wd = decimate_columns(window, f, same_in_window, source=src)
        w_all[k0 : k0 + count, order] = wd[first : first + count]
        # The next window starts at b - pad: keep what this one computed from there on.
        carry_lo = max(0, b - pad)
        carry = window[carry_lo - lo :].copy(order="F") if b < n_samples else None
        if progress is not None:
            progress(b - a)
    trim = settings.trim
    if nd <= 2 * trim:
        raise DataError(
            f"too few samples: {n_samples} samples decimated by {f} leave {nd}, not more than "
            f"the {2 * trim} border samples to trim",
            file=src,
        )
    keep = np.arange(trim, nd - trim)
    keep = keep[np.abs(rest_d[keep]) < REST_LEAK]
    if keep.size < 2:
        raise DataError("the robot is at rest during the whole recording", file=src)
    return PreparedRun(
        label=label,
        t=t0 + keep * f / rate_hz,
        regressor=CompactRegressor(
            _compact(w_all, keep),
            np.concatenate([rows, s_joint]),
            np.concatenate([cols, len(columns) + s_source]),
            n,
            len(columns) + used.size,
        ),
        columns=tuple(columns),
        current=c_all[keep],
        rate_hz=rate_hz / f,
        payload=payload,
        filter=settings,
        source=source,
        raw_samples=n_samples,
        period_s=period_s,
        rest_samples=int(rest.sum()),
        reversal_share=zones_d[keep],
        reversal_coulomb=len(columns) + np.flatnonzero(used),
    )


def _with_sign_cutoff(
    model: RobotModel, q: np.ndarray, qd: np.ndarray, rate_hz: float, settings: FilterSettings
) -> FilterSettings:
    """``settings`` with the Coulomb sign's cut-off this run takes
    (:func:`~.coulombsign.sign_cutoff`), when it has a noise limit: from each drive's encoder
    step and RMS speed on the motor side, where the encoders are (a coupled wrist's joint
    positions mix two motors' steps)."""
    limit = settings.sign_noise_limit
    if limit is None or settings.sign_cutoff <= settings.cutoff_hz:
        return settings
    k = model.robot.transmission()
    speed = np.sqrt(np.mean((qd @ k.T) ** 2, axis=0))
    hz = sign_cutoff(
        settings.sign_cutoff,
        settings.cutoff_hz,
        rate_hz,
        settings.order,
        encoder_steps(q @ k.T),
        speed,
        limit,
    )
    return replace(settings, sign_cutoff_hz=hz)


def _compact(a: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """``a[keep]`` for increasing ``keep``, moved to the front of ``a`` in place.

    A gathered copy of a long run's regressor would double its memory for a moment; with
    ``keep[i] ≥ i`` a block's sources lie at or after its destination and after every
    earlier block's, so nothing is overwritten before it is read. Returns a view of ``a``.
    """
    for s in range(0, keep.size, CHUNK):
        blk = keep[s : s + CHUNK]
        a[s : s + blk.size] = a[blk]
    return a[: keep.size]
