"""Cross-validation: fit IDIM-WLS on the first part of every run, predict the held-out end.

The held-out residual is what tells two model variants apart (e.g. the coupled-wrist friction
forms, docs/model.md): the fitted residual always favours the model with more columns.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from drivegain.errors import InputError
from drivegain.identify import forked
from drivegain.identify.cases import fit_case
from drivegain.identify.design import Design
from drivegain.identify.estimate import r_factor
from drivegain.identify.predict import prediction_quality, predictions

#: Fraction of each run held out (its end) for cross-validation.
CV_FRACTION = 0.3


@dataclass(frozen=True)
class CrossValidation:
    """Fit on the first part of every run, prediction of the held-out end.

    Attributes
    ----------
    fraction
        Fraction of each run held out (its last samples).
    r2, joint_relative
        Per joint on the held-out samples.
    relative_error
        ‖ρ‖/‖Y‖ on the held-out samples.
    train_relative_error
        The same on the fitted samples.
    """

    fraction: float
    r2: np.ndarray
    joint_relative: np.ndarray
    relative_error: float
    train_relative_error: float


def split_runs(designs: Sequence[Design], fraction: float) -> tuple[list[Design], list[Design]]:
    """Each run's first ``1 − fraction`` of rows (to fit) and its held-out end (to predict)."""
    train, test = [], []
    for d in designs:
        split = round(d.rows * (1.0 - fraction))
        train.append(d.subset(slice(0, split)))
        test.append(d.subset(slice(split, None)))
    return train, test


def cross_validate(
    designs: Sequence[Design],
    gains: np.ndarray,
    base_names: Sequence[str],
    fraction: float = CV_FRACTION,
    train_factors: Sequence[np.ndarray] | None = None,
) -> CrossValidation:
    """Hold out the last ``fraction`` of every run, fit IDIM-WLS on the rest, predict it.

    Parameters
    ----------
    designs
        The runs (each split at the same fraction, so every run is held out alike).
    gains
        Drive gains, N·m/A, (n,).
    base_names
        Names of the base parameters.
    fraction
        Held-out fraction of each run, in (0, 1).
    train_factors
        Per run, the R factors of the fitted part's rows (:func:`split_factors`), when the
        caller has them (computed here otherwise).

    Returns
    -------
    CrossValidation
        Held-out and fitted quality.

    Raises
    ------
    InputError
        ``fraction`` is outside (0, 1).
    """
    if not 0.0 < fraction < 1.0:
        raise InputError(f"must be in (0, 1), got {fraction}", key="cv_fraction")
    train, test = split_runs(designs, fraction)
    fit = fit_case("cv", train, gains, base_names, train_factors, covariance=False)
    chi, payloads = fit.coefficients()
    held_out = prediction_quality(predictions(test, fit.gains, chi, payloads))
    return CrossValidation(
        fraction=fraction,
        r2=held_out.r2,
        joint_relative=held_out.joint_relative,
        relative_error=held_out.relative_error,
        train_relative_error=fit.relative_error,
    )


#: Designs with their :func:`split_factors` (whole, fitted part), whose joints' factors another
#: call may reuse.
Factored = tuple[Sequence[Design], Sequence[np.ndarray], Sequence[np.ndarray]]


def split_factors(
    designs: Sequence[Design],
    fraction: float = CV_FRACTION,
    *,
    parallel: bool = False,
    like: Factored | None = None,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per run, the R factors of all its rows and of its fitted part (:func:`split_runs`).

    The fitted part and the held-out end are reduced separately; stacking their two small
    factors and reducing again gives the whole run's, so the cross-validation costs no pass
    over the rows of its own.

    With ``parallel`` (long runs, and not called from a forked child: multiprocessing forbids
    it to fork again), the first run's QRs are made in a forked child while the others' are
    made here (:mod:`.forked`; the same result either way).

    ``like``: other designs of the same runs with their factors at the same ``fraction``
    (another friction form's): a joint whose rows are the same there
    (:meth:`.Design.same_rows`) takes its factors from them, the very numbers its own QRs
    would give.

    Returns
    -------
    whole, train
        Per run, (n, m, m) each.
    """
    if not 0.0 < fraction < 1.0:
        raise InputError(f"must be in (0, 1), got {fraction}", key="cv_fraction")
    known: list[tuple[Design, np.ndarray, np.ndarray] | None] = [None] * len(designs)
    if like is not None:
        ref_designs, ref_whole, ref_train = like
        for i in range(min(len(designs), len(ref_designs))):
            known[i] = (ref_designs[i], ref_whole[i], ref_train[i])
    pairs = forked.map_items(
        "cross-validation factors",
        lambda i: _split_factors(designs[i], fraction, known[i]),
        list(range(len(designs))),
        parallel=parallel,
    )
    return [w for w, _ in pairs], [f for _, f in pairs]


def _split_factors(
    d: Design, fraction: float, known: tuple[Design, np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """One run's whole and fitted-part R factors (:func:`split_factors`); ``known``: another
    design of the run with its whole and fitted-part factors, reused for the joints whose rows
    are the same."""
    same = [] if known is None else [j for j in range(d.n) if d.same_rows(known[0], j)]
    todo = [j for j in range(d.n) if j not in same]
    (train,), (test,) = split_runs([d], fraction)
    fitted, held = train.factors(todo), test.factors(todo)
    whole = np.zeros_like(fitted)
    for j in todo:
        whole[j] = r_factor(np.vstack([fitted[j], held[j]]))
    if known is not None:
        whole[same], fitted[same] = known[1][same], known[2][same]
    return whole, fitted
