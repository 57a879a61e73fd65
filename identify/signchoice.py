"""Which velocity the Coulomb columns take their sign of, chosen by the runs' likelihood.

By default the sign's velocity is filtered well above the position cut-off
(:attr:`~drivegain.identify.signal.FilterSettings.sign_cutoff_hz`, lowered where the encoder is
coarse: :mod:`.coulombsign`). That keeps the sign's zero crossings on a drive that dwells at its
reversals in closed loop, where it halves the gains' error. A drive that follows its trajectory
without dwelling gains nothing from it and pays for the encoder's staircase near each reversal:
on the validation study's exact tracking of the shipped excitation (1e-3° joint quantum) the
higher cut-off left an excess of variance near reversals and a bias on g1 (docs/model.md).

No rule on the encoder alone tells the two apart: the study's closed-loop drives on random
excitations cross one encoder step near a reversal in 1-3 ms, as do the exact-tracking drives
of the shipped one. The currents do. When the rule kept the sign above the position cut-off,
the runs are prepared a second time with the sign at the position cut-off and the
maximum-likelihood fit of runs a and b is made on both; the preparation whose fit explains the
same currents better (smaller :attr:`~drivegain.identify.ml.MLFit.neg_log_lik`) is kept, and
so is its fit: the gains' estimate takes it rather than fitting the same runs again
(:func:`~drivegain.identify.gains.estimate_gains`'s ``fit``). Plain functions.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from drivegain.config.payload import Payload
from drivegain.errors import IdentificationError
from drivegain.identify.design import Design
from drivegain.identify.ml import MLFit, ml_fit
from drivegain.identify.signal import FilterSettings


@dataclass(frozen=True)
class SignChoice:
    """The outcome of :func:`choose_sign`.

    Attributes
    ----------
    chosen
        Index of the candidate kept (0: the first, the rule's).
    sign_cutoff_hz
        Each candidate's sign cut-off (run a's), Hz.
    neg_log_lik
        Each candidate's −2 log L per sample (:attr:`~drivegain.identify.ml.MLFit.neg_log_lik`);
        NaN where its fit failed.
    fit
        The kept candidate's fit, with the errors-in-variables test's sums
        (``ml_fit(..., influence=True)``); None when every fit failed.
    """

    chosen: int
    sign_cutoff_hz: tuple[float, ...]
    neg_log_lik: tuple[float, ...]
    fit: MLFit | None = field(default=None, repr=False, compare=False)

    def note(self) -> str:
        """One line for the report: what was chosen and by how much."""
        kept = self.sign_cutoff_hz[self.chosen]
        others = [
            f"{hz:g} Hz ({_per_sample(nll, self.neg_log_lik[self.chosen])})"
            for i, (hz, nll) in enumerate(zip(self.sign_cutoff_hz, self.neg_log_lik, strict=True))
            if i != self.chosen
        ]
        return (
            f"Coulomb sign's velocity filtered at {kept:g} Hz, chosen by the runs' likelihood "
            f"over {', '.join(others)}"
        )


def _per_sample(nll: float, best: float) -> str:
    if not math.isfinite(nll):
        return "its fit failed"
    if nll == best:  # the same signs after all: a tie keeps the first (the rule's)
        return "the same likelihood"
    return f"−2 log L larger by {nll - best:.3g} per sample"


def at_position_cutoff(settings: FilterSettings | None) -> FilterSettings | None:
    """``settings`` with the Coulomb sign at the position cut-off, when its noise rule kept the
    sign above it; None otherwise (a cut-off given by hand, or the sign there already).

    Parameters
    ----------
    settings
        The settings a run was prepared with (:attr:`PreparedRun.filter`), or None (exact
        derivatives).
    """
    if settings is None or settings.sign_noise_limit is None:
        return None
    if settings.sign_cutoff <= settings.cutoff_hz:
        return None
    return replace(settings, sign_cutoff_hz=settings.cutoff_hz, sign_noise_limit=None)


def has_choice(filters: Iterable[FilterSettings | None]) -> bool:
    """Whether runs prepared with ``filters`` have a second candidate: some run's noise rule
    kept the sign above the position cut-off (:func:`at_position_cutoff`)."""
    return any(at_position_cutoff(f) is not None for f in filters)


def choose_sign(
    candidates: Sequence[tuple[Design, Design]], payload: Payload, *, parallel: bool = False
) -> SignChoice:
    """The candidate preparation of runs a and b whose maximum-likelihood fit is the likeliest.

    Parameters
    ----------
    candidates
        (run a, run b) designs of the same recordings, prepared with different sign cut-offs;
        the same entries in each (checked).
    payload
        Run b's payload.
    parallel
        The runs are long enough for each fit to use a forked child
        (:func:`~drivegain.identify.ml.ml_fit`; the same result either way).

    Returns
    -------
    SignChoice
        The smallest −2 log L per sample; ties, and every fit failing, keep the first. Its
        :attr:`~SignChoice.fit` is the fit :func:`~drivegain.identify.gains.estimate_gains`
        would make of the kept candidate.

    Raises
    ------
    ValueError
        No candidate, or candidates whose entries differ (their likelihoods would not compare).
    """
    if not candidates:
        raise ValueError("no candidate preparation")
    first_a, first_b = candidates[0]
    for a, b in candidates[1:]:
        if not (
            np.array_equal(a.run.current, first_a.run.current)
            and np.array_equal(b.run.current, first_b.run.current)
        ):
            raise ValueError("the candidates' runs keep different entries: not comparable")
    values = []
    fits: list[MLFit | None] = []
    for a, b in candidates:
        try:
            # With the test's sums, as the gains' estimate fits: the winner's fit is reused
            # there. They come from the covariance pass: 1.06 → 1.10-1.18 s per fit on two
            # 240 s runs at 250 Hz, against a whole fit saved.
            fit = ml_fit(a, b, payload, parallel=parallel, influence=True)
        except IdentificationError:
            # a preparation the fit cannot use is not the likelier one
            fit = None
        fits.append(fit)
        values.append(math.nan if fit is None else fit.neg_log_lik)
    finite = [(v, i) for i, v in enumerate(values) if math.isfinite(v)]
    chosen = min(finite)[1] if finite else 0
    cutoffs = tuple(
        math.nan if a.run.filter is None else a.run.filter.sign_cutoff for a, _ in candidates
    )
    return SignChoice(
        chosen=chosen, sign_cutoff_hz=cutoffs, neg_log_lik=tuple(values), fit=fits[chosen]
    )
