"""The Coulomb sign's velocity, chosen by the runs' likelihood (identify.signchoice).

Two kinds of drive the noise rule on the encoder cannot tell apart: the simulated cell's drives in
closed loop, which dwell at each reversal (the higher sign cut-off follows them), and drives that
track the shipped excitation exactly with a coarse 1e-3° joint quantum (the higher cut-off only
adds the encoder's staircase near reversals). The likelihood of the same currents tells them
apart; the fit's −2 log L is checked against scipy's Gaussian density of its own residuals.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from drivegain.errors import IdentificationError
from drivegain.identify.design import Design, make_design
from drivegain.identify.ml import ml_fit
from drivegain.identify.mlmodel import predict, run_pair
from drivegain.identify.signchoice import at_position_cutoff, choose_sign
from drivegain.validation.cell import closed_loop_run
from drivegain.validation.estimators import run_designs, seed_runs, seed_world
from drivegain.validation.scenarios import SCENARIOS, scenario_rng
from drivegain.validation.world import World, prepare


def _scenario(key: str):
    return next(sc for sc in SCENARIOS if sc.key == key)


def _both(world: World, runs) -> tuple[list[Design], list[Design]]:
    """Designs of ``runs`` with the rule's sign cut-off and with the position cut-off's."""
    rule = [make_design(prepare(world, r), world.base, world.form, world.robot) for r in runs]
    other = at_position_cutoff(rule[0].run.filter)
    assert other is not None
    there = replace(world, settings=other)
    pos = [make_design(prepare(there, r), world.base, world.form, world.robot) for r in runs]
    return rule, pos


@pytest.fixture(scope="module")
def dwelling(world: World) -> tuple[World, list[Design], list[Design]]:
    """Runs a and b of the shipped excitation by the closed-loop drives (they dwell)."""
    sc = _scenario("closed-loop")
    rng = scenario_rng(sc, 0)
    runs = [
        closed_loop_run(world, None, sc, rng, "unloaded"),
        closed_loop_run(world, world.payload, sc, rng, "loaded"),
    ]
    return (world, *_both(world, runs))


def test_settings_with_the_sign_at_the_position_cutoff(world: World) -> None:
    st = world.settings  # the rule's: 8 × the cut-off, with a noise limit
    assert st.sign_noise_limit is not None and st.sign_cutoff > st.cutoff_hz
    there = at_position_cutoff(st)
    assert there is not None
    assert there.sign_cutoff == there.cutoff_hz == st.cutoff_hz
    assert there.sign_noise_limit is None
    assert (
        replace(there, sign_cutoff_hz=st.sign_cutoff_hz, sign_noise_limit=st.sign_noise_limit) == st
    )
    assert at_position_cutoff(there) is None  # the sign there already
    assert at_position_cutoff(replace(st, sign_noise_limit=None)) is None  # given by hand
    assert at_position_cutoff(None) is None  # exact derivatives


def test_drives_that_dwell_keep_the_higher_cutoff(dwelling) -> None:
    world, rule, pos = dwelling
    choice = choose_sign([(rule[0], rule[1]), (pos[0], pos[1])], world.payload)
    assert choice.chosen == 0
    assert choice.sign_cutoff_hz == (rule[0].run.filter.sign_cutoff, world.settings.cutoff_hz)
    assert choice.sign_cutoff_hz[0] > choice.sign_cutoff_hz[1]
    gap = choice.neg_log_lik[1] - choice.neg_log_lik[0]
    assert gap > 1.0  # per sample: e^(1/6) ≈ 1.18 × the variance of every drive, or more
    assert "chosen by the runs' likelihood" in choice.note()
    # The kept candidate's fit, with the test's sums, for the gains' estimate to reuse.
    assert choice.fit is not None and choice.fit.influence is not None
    assert choice.fit.neg_log_lik == choice.neg_log_lik[0]
    # The order of the candidates does not decide.
    again = choose_sign([(pos[0], pos[1]), (rule[0], rule[1])], world.payload)
    assert again.chosen == 1 and again.neg_log_lik == choice.neg_log_lik[::-1]


@pytest.mark.parametrize("seed", [0, 1])
def test_exact_tracking_of_the_shipped_excitation_takes_the_position_cutoff(
    world: World, seed: int
) -> None:
    sc = _scenario("torque-0.05")
    w = seed_world(world, sc, seed)
    runs = seed_runs(w, sc, scenario_rng(sc, seed))
    rule, pos = _both(w, runs[:2])
    choice = choose_sign([(rule[0], rule[1]), (pos[0], pos[1])], w.payload)
    assert choice.chosen == 1
    # The study's preparation is that choice, for all three runs.
    designs = run_designs(w, runs)
    assert len(designs) == 3
    for d in designs:
        assert d.run.filter is not None and d.run.filter.sign_cutoff == w.settings.cutoff_hz
    np.testing.assert_array_equal(designs[0].run.regressor.series, pos[0].run.regressor.series)


def test_neg_log_lik_is_the_gaussian_density_of_the_fits_residuals(dwelling) -> None:
    world, rule, _ = dwelling
    a, b = rule
    fit = ml_fit(a, b, world.payload)
    assert np.any(fit.kappa > 0.1)  # entries near reversals count with their own variance
    runs = run_pair(a, b, world.payload)
    kt_inv = np.linalg.inv(np.asarray(a.kt, float))
    total, samples = 0.0, 0
    for r in runs:
        e = r.v - predict(fit.theta, r, kt_inv)[0]
        s = np.sqrt(1.0 + fit.kappa[None, :] * r.reversal)  # S_k, per entry
        # e_k ~ N(0, S_k Σ S_k): the density of ε = S⁻¹e under Σ, and the Jacobian log det S
        logpdf = stats.multivariate_normal(np.zeros(a.n), fit.noise).logpdf(e / s)
        total += float(np.sum(-2.0 * logpdf + 2.0 * np.sum(np.log(s), axis=1)))
        samples += r.samples
    constant = a.n * np.log(2.0 * np.pi)
    assert fit.neg_log_lik == pytest.approx(total / samples - constant, rel=0, abs=1e-6)


def test_a_candidate_whose_fit_fails_is_not_chosen(dwelling, monkeypatch) -> None:
    world, rule, pos = dwelling
    import drivegain.identify.signchoice as sc

    real = sc.ml_fit

    def failing_on_the_first(a, b, payload, **kw):
        if a is rule[0]:
            raise IdentificationError("no")
        return real(a, b, payload, **kw)

    monkeypatch.setattr(sc, "ml_fit", failing_on_the_first)
    choice = choose_sign([(rule[0], rule[1]), (pos[0], pos[1])], world.payload)
    assert choice.chosen == 1 and np.isnan(choice.neg_log_lik[0])
    assert choice.fit is not None and choice.fit.neg_log_lik == choice.neg_log_lik[1]
    assert "its fit failed" in choice.note()

    def failing(a, b, payload, **kw):
        raise IdentificationError("no")

    monkeypatch.setattr(sc, "ml_fit", failing)
    none = choose_sign([(rule[0], rule[1]), (pos[0], pos[1])], world.payload)
    assert none.chosen == 0 and none.fit is None  # every fit failed: the first, no fit


def test_candidates_of_other_entries_are_refused(dwelling) -> None:
    world, rule, pos = dwelling
    with pytest.raises(ValueError, match="no candidate"):
        choose_sign([], world.payload)
    with pytest.raises(ValueError, match="not comparable"):
        choose_sign([(rule[0], rule[1]), (pos[1], pos[0])], world.payload)
