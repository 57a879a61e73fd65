"""Statistics of the Monte Carlo: bias, spread, coverage of the reported σ, paired ratios.

Errors are relative to the simulation truth, in %; coverage counts how often the reported
±2σ interval holds the truth. Comparisons between two estimators resample seeds in pairs, so
the noise they share cancels out of the ratio.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

from drivegain.errors import InputError
from drivegain.identify.decimate import parallel_decimate
from drivegain.identify.gains import DEFAULT_ALPHA_GRID
from drivegain.validation.estimators import METHODS, OURS, SAME_INFORMATION, Method, SeedResult
from drivegain.validation.scenarios import ROOT_SEED
from drivegain.validation.world import World


def rel_errors(results: Sequence[SeedResult], key: str, truth: np.ndarray) -> np.ndarray:
    """(seeds, n) relative gain errors of method ``key``, % (seeds where it failed left out)."""
    rows = [100.0 * (r.gains[key] / truth - 1.0) for r in results if key in r.gains]
    return np.array(rows).reshape(-1, truth.size)


def bootstrap_ratio(
    err: np.ndarray, ref: np.ndarray, rng: np.random.Generator, draws: int = 2000
) -> tuple[float, float, float]:
    """RMS(err)/RMS(ref) over paired seeds (rows), with a 95 % bootstrap interval.

    Parameters
    ----------
    err, ref
        (seeds, k) errors of two estimators on the same data (any unit, the same for both).
    rng
        Random generator of the resampling.
    draws
        Bootstrap resamples.

    Returns
    -------
    tuple of float
        The ratio and the 2.5 % and 97.5 % quantiles of its bootstrap distribution.

    Seeds are resampled together so the shared noise cancels out of the comparison.
    """
    a = np.sum(err**2, axis=1)
    b = np.sum(ref**2, axis=1)
    ratio = math.sqrt(a.sum() / b.sum())
    idx = rng.integers(0, a.size, size=(draws, a.size))
    boot = np.sqrt(a[idx].sum(axis=1) / b[idx].sum(axis=1))
    lo, hi = np.quantile(boot, [0.025, 0.975])
    return ratio, float(lo), float(hi)


def wilson(p: float, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson interval of a proportion ``p`` observed on ``n`` independent trials.

    ``z`` is the normal quantile of the interval; returns NaNs when ``n`` is 0.
    """
    if n == 0:
        return math.nan, math.nan
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return centre - half, centre + half


def _std(r: SeedResult, key: str) -> np.ndarray:
    std = r.std[key]
    if std is None:
        raise InputError(f"method {key} reports no standard deviations", key="method")
    return std


def z_scores(results: Sequence[SeedResult], key: str, truth: np.ndarray) -> np.ndarray:
    """(seeds, n) errors in reported standard deviations, (ĝ − g)/σ̂, dimensionless.

    Raises
    ------
    InputError
        If method ``key`` reports no standard deviations.
    """
    return np.array([(r.gains[key] - truth) / _std(r, key) for r in results if key in r.gains])


def method_stats(
    results: Sequence[SeedResult], world: World, m: Method, factor: float = 1.0
) -> dict[str, Any]:
    """Bias, spread, RMS error, coverage, runtime and payload errors of one estimator.

    Parameters
    ----------
    results
        The seeds of one scenario.
    world
        The simulated robot (its truth is the reference).
    m
        The estimator.
    factor
        Variance factor of the decimated noise (:func:`decimated_noise_factor`); the coverage
        the σ would have if multiplied by its square root is reported as a diagnostic.
    """
    g = world.truth.gains
    e = rel_errors(results, m.key, g)
    out: dict[str, Any] = {
        "key": m.key,
        "label": m.label,
        "ablation": m.ablation,
        "seeds": int(e.shape[0]),
        "failures": sorted({r.failures[m.key] for r in results if m.key in r.failures}),
        "bias_pct": e.mean(axis=0).tolist(),
        "spread_pct": e.std(axis=0, ddof=1).tolist() if e.shape[0] > 1 else [math.nan] * g.size,
        "rmse_pct": np.sqrt(np.mean(e**2, axis=0)).tolist(),
        "rmse_all_pct": float(np.sqrt(np.mean(e**2))),
        "max_abs_pct": float(np.abs(e).max()) if e.size else math.nan,
        "median_abs_pct": float(np.median(np.abs(e))) if e.size else math.nan,
        "seconds_median": float(
            np.median([r.seconds[m.key] for r in results if m.key in r.seconds])
        ),
    }
    if m.reports_std:
        z = z_scores(results, m.key, g)
        inside = np.abs(z) <= 2.0
        out["coverage"] = inside.mean(axis=0).tolist()
        out["coverage_all"] = float(inside.mean())
        out["coverage_all_ci"] = list(wilson(float(inside.mean()), int(inside.size)))
        out["coverage_if_scaled"] = float(np.mean(np.abs(z) <= 2.0 * math.sqrt(factor)))
        out["z_mean"] = z.mean(axis=0).tolist()
        out["z_std"] = z.std(axis=0, ddof=1).tolist() if z.shape[0] > 1 else [math.nan] * g.size
        out["rel_std_pct_median"] = np.median(
            [100 * _std(r, m.key) / np.abs(r.gains[m.key]) for r in results if m.key in r.gains],
            axis=0,
        ).tolist()
        out.update(payload_z_stats(results, m.key, world))
    for which, nominal in (("b", world.payload.values), ("c", world.validation.values)):
        out[f"payload_{which}_rms_pct"] = payload_rms(results, m.key, nominal, which).tolist()
    flags = [r.at_edge[m.key] for r in results if m.key in r.at_edge]
    out["at_edge"] = float(np.mean(flags)) if flags else math.nan
    return out


def payload_z(results: Sequence[SeedResult], key: str, truth: np.ndarray, which: str) -> np.ndarray:
    """(seeds, 10) z of the payload parameters of run ``which`` (b, c) fitted with ``key``'s gains.

    z = (χ̂ − χ)/σ̂ with the reported σ of the Case 2 fit; NaN where the parameter was known
    (σ = 0: nothing estimated) or the fit failed.
    """
    vals = "payload_b" if which == "b" else "payload_c"
    rows = []
    for r in results:
        if key not in getattr(r, vals):
            continue
        std = np.asarray(getattr(r, vals + "_std")[key], dtype=float)
        est = np.asarray(getattr(r, vals)[key], dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            rows.append(np.where(std > 0, (est - truth) / std, np.nan))
    return np.array(rows).reshape(-1, truth.size)


def payload_z_stats(results: Sequence[SeedResult], key: str, world: World) -> dict[str, Any]:
    """Coverage of the payload parameters' ±2σ and the spread and mean of their z.

    Pooled over both payloads (runs b and c) and every estimated parameter; per parameter for
    each payload. The σ are those of the Case 2 fit with ``key``'s gains. The parameters of run
    b's payload that are known (its mass) are left out: the gains were scaled to reproduce
    them, so their Case 2 estimates are the given values again and say nothing about σ.
    """
    out: dict[str, Any] = {}
    pooled = []
    for which, truth in (("b", world.payload.values), ("c", world.validation.values)):
        z = payload_z(results, key, truth, which)
        if which == "b":
            z[:, world.payload.known_mask()] = np.nan
        pooled.append(z[np.isfinite(z)])
        with warnings.catch_warnings():
            # A known parameter has no z at all: its empty column is NaN, not a warning.
            warnings.simplefilter("ignore", RuntimeWarning)
            out[f"payload_{which}_z_std"] = (
                np.nanstd(z, axis=0, ddof=1) if z.shape[0] > 1 else np.full(truth.size, np.nan)
            ).tolist()
            out[f"payload_{which}_z_mean"] = np.nanmean(z, axis=0).tolist()
    zz = np.concatenate(pooled) if pooled else np.empty(0)
    inside = float(np.mean(np.abs(zz) <= 2.0)) if zz.size else math.nan
    out["payload_coverage_all"] = inside
    out["payload_coverage_all_ci"] = list(wilson(inside, int(zz.size)))
    return out


def payload_rms(
    results: Sequence[SeedResult], key: str, truth: np.ndarray, which: str
) -> np.ndarray:
    """RMS relative error (% of ``truth``) of each payload parameter of run ``which`` (b, c)."""
    store = "payload_b" if which == "b" else "payload_c"
    est = np.array([getattr(r, store)[key] for r in results if key in getattr(r, store)])
    if est.size == 0:
        return np.full(truth.size, math.nan)
    return np.asarray(np.sqrt(np.mean((100 * (est - truth) / np.abs(truth)) ** 2, axis=0)))


def payload_coverage(
    results: Sequence[SeedResult], key: str, truth: np.ndarray, which: str
) -> np.ndarray:
    """Coverage of the reported 2σ of each payload parameter of run ``which`` (b, c).

    The gains are taken as exact. A parameter known in advance (σ = 0) counts as not covered:
    its z is 0/0, which compares false (kept so from the first study, whose numbers are
    published).
    """
    vals = "payload_b" if which == "b" else "payload_c"
    stds = vals + "_std"
    with np.errstate(divide="ignore", invalid="ignore"):  # σ = 0: not covered, on purpose
        z = np.array(
            [
                (getattr(r, vals)[key] - truth) / getattr(r, stds)[key]
                for r in results
                if key in getattr(r, vals)
            ]
        )
    return np.asarray(np.mean(np.abs(z) <= 2.0, axis=0))


def joint_ratios(err: np.ndarray, ref: np.ndarray, rng: np.random.Generator) -> list[list[float]]:
    """:func:`bootstrap_ratio` of each joint (column) alone, in joint order: per joint, the
    ratio and its 95 % interval."""
    return [list(bootstrap_ratio(err[:, [j]], ref[:, [j]], rng)) for j in range(err.shape[1])]


def scenario_summary(
    results: Sequence[SeedResult], world: World, factor: float = 1.0
) -> dict[str, Any]:
    """All statistics of one noise scenario (``factor``: see :func:`method_stats`)."""
    g = world.truth.gains
    rng = np.random.default_rng((ROOT_SEED, 7))
    stats = {m.key: method_stats(results, world, m, factor) for m in METHODS}
    ref = rel_errors(results, OURS, g)
    for m in METHODS:
        if m.key == OURS:
            continue
        e = rel_errors(results, m.key, g)
        if e.shape != ref.shape:
            continue
        stats[m.key]["ratio_to_ours"] = list(bootstrap_ratio(e, ref, rng))
        stats[m.key]["ratio_to_ours_joint"] = joint_ratios(e, ref, rng)
    # A stream of its own, so that the ratios to ours stay those of earlier runs.
    rng = np.random.default_rng((ROOT_SEED, 8))
    for rival, mine in SAME_INFORMATION.items():
        e, e_mine = rel_errors(results, rival, g), rel_errors(results, mine, g)
        if e.size and e.shape == e_mine.shape:
            stats[rival]["ratio_to_counterpart_joint"] = joint_ratios(e, e_mine, rng)
    case = {
        "case1": {
            "payload_b_rms_pct": payload_rms(results, "case1", world.payload.values, "b").tolist(),
            "payload_c_rms_pct": payload_rms(
                results, "case1", world.validation.values, "c"
            ).tolist(),
            "payload_b_coverage": payload_coverage(
                results, "case1", world.payload.values, "b"
            ).tolist(),
        },
        "case2": {
            "payload_b_rms_pct": stats[OURS]["payload_b_rms_pct"],
            "payload_c_rms_pct": stats[OURS]["payload_c_rms_pct"],
            "payload_b_coverage": payload_coverage(
                results, OURS, world.payload.values, "b"
            ).tolist(),
            "payload_c_coverage": payload_coverage(
                results, OURS, world.validation.values, "c"
            ).tolist(),
        },
        "error_norms": {
            k: np.mean([r.error_norms[k] for r in results if k in r.error_norms], axis=0).tolist()
            for k in ("case1", OURS)
        },
    }
    alphas = np.array([r.alpha for r in results])
    blocks = np.array([r.block for r in results])
    grid = (min(DEFAULT_ALPHA_GRID), max(DEFAULT_ALPHA_GRID))
    return {
        "seeds": len(results),
        "methods": stats,
        "cases": case,
        "preparation": preparation_summary(results),
        "alpha": {
            "median": float(np.median(alphas)),
            "min": float(alphas.min()),
            "max": float(alphas.max()),
            "grid": list(grid),
            "at_grid_ends": float(
                np.mean((alphas <= grid[0] * 1.0001) | (alphas >= grid[1] * 0.9999))
            ),
        },
        "block": {"median": float(np.median(blocks)), "max": float(blocks.max())},
    }


def preparation_summary(results: Sequence[SeedResult]) -> dict[str, Any]:
    """How the seeds' runs were prepared and fitted, beside what they gave.

    Returns
    -------
    dict
        ``sign_at_position``: share of the seeds (with filtered derivatives) whose Coulomb
        sign was taken at the position cut-off (by the encoder rule or by the likelihood's
        choice; None when every seed has exact derivatives), and ``sign_cutoff_hz``: the sign
        cut-offs used, sorted, each once; ``case2_left_out_seeds``: share of the seeds whose
        Case 2 (ours, run b) left entries out near misfit reversals, and
        ``case2_left_out_median``: the median share of entries left out over those seeds
        (None when none did).
    """
    sign = np.array([r.sign_cutoff_hz for r in results], dtype=float)
    position = np.array([r.position_cutoff_hz for r in results], dtype=float)
    filtered = np.isfinite(sign)
    left = np.array([r.left_out[OURS] for r in results if OURS in r.left_out], dtype=float)
    some = left[left > 0.0]
    return {
        "sign_at_position": float(np.mean(sign[filtered] == position[filtered]))
        if filtered.any()
        else None,
        "sign_cutoff_hz": sorted({float(x) for x in sign[filtered]}),
        "case2_left_out_seeds": float(np.mean(left > 0.0)) if left.size else None,
        "case2_left_out_median": float(np.median(some)) if some.size else None,
    }


def decimated_noise_factor(world: World, columns: int = 200, seed: int = 1) -> float:
    """Variance of decimated white noise seen by low-frequency regressors, over its variance.

    White noise at the sample rate goes through the same parallel decimation as the data; its
    projection on the trajectory's harmonics (base frequency × 1..4·harmonics, where the
    regressor columns live) has a variance per component this many times the per-sample
    variance of the decimated noise. 1 means white; an estimator that takes the decimated
    equation errors as white underestimates its variances by this factor.

    Parameters
    ----------
    world
        The simulated robot (sample rate, decimation, trajectory harmonics).
    columns
        Independent noise series averaged.
    seed
        Seed of the noise, in the study's stream ``(ROOT_SEED, 11, seed)``.
    """
    rng = np.random.default_rng((ROOT_SEED, 11, seed))
    x = rng.standard_normal((world.t.size, columns))
    (y,) = parallel_decimate([x], world.settings.decimate, world.settings.trim)
    t = np.arange(y.shape[0]) * world.settings.decimate / world.rate_hz
    f0 = world.fourier.base_frequency_hz
    cols = [
        fn(2 * np.pi * f0 * k * t)
        for k in range(1, 4 * world.fourier.harmonics + 1)
        for fn in (np.sin, np.cos)
    ]
    q, _ = np.linalg.qr(np.column_stack(cols))
    return float(np.var(q.T @ y) / np.var(y))
