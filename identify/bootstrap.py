"""A residual block bootstrap of the maximum-likelihood fit: a second σ beside the HAC one.

The reported σ of the gains (:mod:`.autocov`) rests on a model of the errors: a stationary
autocovariance over a few lags, corrected for the fit. The bootstrap asks the data instead.
Each replicate keeps the regressors (positions and their derivatives, so any error they carry
is the same in every replicate) and the fitted model currents, adds the fit's own residuals
resampled in circular blocks of consecutive samples, and is fitted again by
:func:`~.ml.ml_fit` from the estimate. The spread of the replicates' gains is the bootstrap σ.

- Blocks keep what the residuals have within a block length: the autocorrelation the
  anti-aliasing filter gives, slower correlation up to that length, and the coupling between
  drives (one block is the same samples of every drive).
- The entries near reversals have a larger variance (:class:`~.mlmodel.Whitening`): the
  residuals are divided by their scale √(1 + κ_i s_ki) before resampling and multiplied by the
  scale of the place they are moved to, so the replicates keep that pattern.
- The fit takes p directions out of the residuals; they are scaled by √(rows / (rows − p)).

Replicate r draws from ``numpy.random.default_rng((seed, r))``, so the result does not depend
on how the replicates are split between processes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from drivegain.config.payload import Payload
from drivegain.errors import IdentificationError, InputError
from drivegain.identify import forked
from drivegain.identify.design import Design
from drivegain.identify.ml import MLFit, ml_fit
from drivegain.identify.mlmodel import RunArrays, predict


@dataclass(frozen=True)
class BootstrapSpread:
    """The replicates of a residual block bootstrap and their spread.

    Attributes
    ----------
    replicates
        Replicates asked for.
    block
        Samples per resampled block (decimated samples).
    seed
        Seed of the replicates' random streams.
    estimates
        Gains (N·m/A) then unknown payload parameters (SI) of each replicate whose fit
        succeeded, (replicates − failed, n + nu).
    n
        Number of drives (the first ``n`` columns of ``estimates`` are gains).
    failed
        Replicates whose fit failed (not counted in the spread).
    """

    replicates: int
    block: int
    seed: int
    estimates: np.ndarray
    n: int
    failed: int

    @property
    def std(self) -> np.ndarray:
        """Standard deviation over the replicates of every column of ``estimates``."""
        return np.asarray(np.std(self.estimates, axis=0, ddof=1))

    @property
    def gain_std(self) -> np.ndarray:
        """Bootstrap σ of the gains, N·m/A, (n,)."""
        return self.std[: self.n]

    @property
    def payload_std(self) -> np.ndarray:
        """Bootstrap σ of the unknown payload parameters (SI), (nu,)."""
        return self.std[self.n :]


def block_length(samples: int, lag: int) -> int:
    """Samples per block: twice the covariance's longest lag plus one, at least ∛samples.

    Parameters
    ----------
    samples
        Samples of the shortest run.
    lag
        Longest lag of the errors' autocovariance the fit's covariance used (decimated samples).
    """
    return int(min(samples, max(2 * lag + 1, math.ceil(samples ** (1.0 / 3.0)))))


def circular_blocks(samples: int, block: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of a circular block resample: ⌈samples/block⌉ blocks of ``block`` consecutive
    samples from random starts (wrapping past the end), cut to ``samples``.

    Parameters
    ----------
    samples
        Length of the series.
    block
        Samples per block, 1..samples.
    rng
        Random stream of the replicate.
    """
    if not 1 <= block <= samples:
        raise InputError(f"bootstrap block of {block} samples for a run of {samples}")
    count = -(-samples // block)
    starts = rng.integers(0, samples, size=count)
    idx = (starts[:, None] + np.arange(block)[None, :]).ravel()[:samples]
    return np.asarray(idx % samples)


def _scale(run: RunArrays, kappa: np.ndarray) -> np.ndarray:
    """√(1 + κ_i s_ki) of every entry, (N, n) (ones away from reversals)."""
    if run.reversal is None:
        return np.ones_like(run.v)
    return np.sqrt(1.0 + kappa[None, :] * run.reversal)


#: Fewest replicates accepted (a standard deviation from fewer is mostly noise: ±50 % at 10).
MIN_REPLICATES = 10
#: Share of replicates whose fit may fail before the bootstrap is not reported.
MAX_FAILED_SHARE = 0.1


def bootstrap_fit(
    a: Design,
    b: Design,
    payload: Payload,
    fit: MLFit,
    replicates: int,
    *,
    runs: Sequence[RunArrays],
    seed: int = 0,
    parallel: bool = False,
) -> BootstrapSpread:
    """Residual block bootstrap of an ML fit of runs a and b.

    Parameters
    ----------
    a, b, payload
        As given to :func:`~.ml.ml_fit`.
    fit
        The fit of the data.
    replicates
        Number of replicates, at least :data:`MIN_REPLICATES`.
    runs
        The model's arrays of a and b the fit used (:func:`~.mlmodel.run_pair`).
    seed
        Seed of the replicates' streams.
    parallel
        Fit about half of the replicates in a forked child (:mod:`.forked`; the same result).

    Returns
    -------
    BootstrapSpread

    Raises
    ------
    InputError
        Fewer than :data:`MIN_REPLICATES` replicates asked for.
    IdentificationError
        More than :data:`MAX_FAILED_SHARE` of the replicates could not be fitted.
    """
    if replicates < MIN_REPLICATES:
        raise InputError(
            f"--bootstrap needs at least {MIN_REPLICATES} replicates, got {replicates}",
            key="bootstrap",
        )
    theta = fit.theta
    kt_inv = np.linalg.inv(np.asarray(a.kt, float))
    rows = sum(r.samples for r in runs) * a.n
    inflate = math.sqrt(rows / max(rows - theta.size, 1))
    block = block_length(min(r.samples for r in runs), fit.lag)
    # Per run: model currents, and residuals with the reversal scale taken out.
    parts = []
    for r in runs:
        fitted = predict(theta, r, kt_inv)[0]
        scale = _scale(r, fit.kappa)
        parts.append((r, fitted, scale, inflate * (r.v - fitted) / scale))

    def one(rep: int) -> np.ndarray | None:
        rng = np.random.default_rng((seed, rep))
        sample = []
        for r, fitted, scale, std_resid in parts:
            idx = circular_blocks(r.samples, block, rng)
            sample.append(replace(r, v=fitted + scale * std_resid[idx]))
        try:
            again = ml_fit(a, b, payload, start=theta, runs=sample)
        except IdentificationError:
            return None
        return np.concatenate([again.gains, again.payload_unknown])

    halves = [range(0, replicates // 2), range(replicates // 2, replicates)]
    done = forked.map_items(
        "bootstrap replicates", lambda reps: [one(k) for k in reps], halves, parallel=parallel
    )
    results = [x for half in done for x in half]
    ok = [x for x in results if x is not None]
    failed = replicates - len(ok)
    if failed > MAX_FAILED_SHARE * replicates:
        raise IdentificationError(
            f"bootstrap: {failed} of {replicates} replicates could not be fitted (the fit is "
            "not stable under its own residuals; its σ should not be trusted either)"
        )
    return BootstrapSpread(
        replicates=replicates,
        block=block,
        seed=seed,
        estimates=np.array(ok),
        n=a.n,
        failed=failed,
    )
