"""The paper's procedure on noise-free simulated TX-40 runs: exact answers expected."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from drivegain.config.robot import WristFriction
from drivegain.errors import InputError
from drivegain.identify.crossval import cross_validate
from drivegain.identify.design import coupling_factor, make_design
from drivegain.identify.gains import identify_gains
from drivegain.identify.procedure import GivenGains, Options, Problem, run_procedure
from drivegain.identify.weighting import drive_noise_weights


def _rel(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b) / np.abs(b)))


@pytest.mark.parametrize("form", list(WristFriction))
def test_noise_free_gains_and_payload_are_exact(world, exact_run, form: WristFriction) -> None:
    """Gains to 1e-6 and all 10 payload parameters to 1e-6, for both friction forms."""
    a = exact_run(0, None, friction=form, label="unloaded")
    b = exact_run(1, world.payload, friction=form, label="loaded")
    res = run_procedure(
        Problem(robot=world.robot, bases=world.bases, unloaded=a, loaded=b),
        Options(friction=form),
    )
    truth = world.truth
    gain_err = _rel(res.gains, truth.gains)
    print(f"\n[{form.value}] gains {np.round(res.gains, 6)} max relative error {gain_err:.2e}")
    assert res.gains_source == "identified"
    assert gain_err < 1e-6
    payload = res.case2.payloads[0]
    pay_err = _rel(payload.values, world.payload.values)
    print(f"[{form.value}] payload (Case 2) max relative error {pay_err:.2e}")
    assert pay_err < 1e-6
    # Case 1 uses the a priori gains (up to 24 % off): its payload is visibly wrong.
    assert _rel(res.case1.payloads[0].values, world.payload.values) > 1e-2
    assert res.case2.relative_error < 1e-9 < res.case1.relative_error
    # The base parameters are those of the truth, regrouped.
    chi = world.bases[form].regroup(
        __import__("drivegain.dynamics.params", fromlist=["x"]).truth_vector(world.robot, truth)
    )
    np.testing.assert_allclose(res.case2.base, chi, rtol=1e-6, atol=1e-9)
    # The other friction form cannot fit this data exactly.
    other = next(f for f in WristFriction if f is not form)
    assert res.forms[other].case.relative_error > 1e3 * res.forms[form].case.relative_error
    assert res.better_form() is form
    assert not res.warnings


def test_known_payload_subset_sets_the_scale(world, exact_run) -> None:
    """Any known subset works: here mass and first moments known, the inertia unknown."""
    known = replace(world.payload, known=("M", "MX", "MY", "MZ"))
    a = exact_run(0, None, label="unloaded")
    b = exact_run(1, known, label="loaded")
    res = run_procedure(
        Problem(robot=world.robot, bases=world.bases, unloaded=a, loaded=b), Options()
    )
    assert _rel(res.gains, world.truth.gains) < 1e-6
    assert res.wtls is not None and res.wtls.payload_names == ["XX", "XY", "XZ", "YY", "YZ", "ZZ"]
    np.testing.assert_allclose(res.wtls.payload_unknown, world.payload.values[:6], rtol=1e-6)


def test_validation_payload_table_5(world, exact_run) -> None:
    a = exact_run(0, None, label="unloaded")
    b = exact_run(1, world.payload, label="loaded")
    c = exact_run(2, world.validation, label="validation")
    res = run_procedure(
        Problem(robot=world.robot, bases=world.bases, unloaded=a, loaded=b, validation=c),
        Options(compare_forms=False),
    )
    assert set(res.validation) == {"case1", "case2"}
    v2 = res.validation["case2"].payloads[0]
    assert v2.name == world.validation.name
    assert _rel(v2.values, world.validation.values) < 1e-6
    assert _rel(res.validation["case1"].payloads[0].values, world.validation.values) > 1e-2


def test_given_gains_skip_wtls(world, exact_run) -> None:
    a = exact_run(0, None, label="unloaded")
    b = exact_run(1, world.payload, label="loaded")
    given = GivenGains(world.truth.gains.copy(), np.full(6, 0.01), "test")
    res = run_procedure(
        Problem(robot=world.robot, bases=world.bases, unloaded=a, loaded=b),
        Options(gains=given, compare_forms=False),
    )
    assert res.wtls is None and res.case2 is None
    assert res.case1.name == "given" and res.gains_source == "test"
    np.testing.assert_array_equal(res.gains, world.truth.gains)
    assert _rel(res.final.payloads[0].values, world.payload.values) < 1e-6


def test_unloaded_only_uses_a_priori_gains(world, exact_run) -> None:
    a = exact_run(0, None, label="unloaded")
    res = run_procedure(
        Problem(robot=world.robot, bases=world.bases, unloaded=a), Options(compare_forms=False)
    )
    assert res.gains_source == "apriori" and res.gains_std is None
    np.testing.assert_array_equal(res.gains, world.robot.apriori_gains)
    assert not res.final.payloads
    # Cross-validation predicts the held-out end of an exact run exactly... up to the wrong
    # gains, which the base parameters partly absorb.
    assert res.cv.relative_error < 1.0


def test_drive_noise_weights_equalise_the_current_noise(world) -> None:
    g = world.truth.gains
    # Without coupling, equal current noise: weights in proportion to the gains.
    c = drive_noise_weights(np.eye(6), g, 0.02 * np.abs(g))
    np.testing.assert_allclose(c / c[0], np.abs(g) / abs(g[0]), rtol=1e-9)
    assert np.exp(np.mean(np.log(c))) == pytest.approx(1.0)
    # TX-40 coupling: drive 6's noise also reaches joint 5; the weighted noise of every V
    # column, averaged over the rows it appears in, comes out equal.
    kt = coupling_factor(world.robot)
    sigma_v = np.array([0.05, 0.04, 0.03, 0.02, 0.02, 0.01])
    sigma = np.sqrt(((kt**2) * (g**2)[None, :]) @ sigma_v**2)
    c = drive_noise_weights(kt, g, sigma)
    present = kt != 0
    q = [
        np.mean(c[m] ** 2 * kt[present[:, m], m] ** 2 * sigma_v[m] ** 2 / sigma[present[:, m]] ** 2)
        for m in range(6)
    ]
    np.testing.assert_allclose(q, q[0], rtol=1e-6)


def test_bad_inputs_raise_input_errors(world, exact_run) -> None:
    """A run in the wrong role, a bad α or held-out fraction: InputError naming the key."""
    a = exact_run(0, None, label="unloaded", duration=5.0)
    b = exact_run(1, world.payload, label="loaded", duration=5.0)
    with pytest.raises(InputError, match="must be unloaded") as exc:
        run_procedure(Problem(robot=world.robot, bases=world.bases, unloaded=b), Options())
    assert exc.value.key == "payload"
    with pytest.raises(InputError, match="has no payload"):
        run_procedure(
            Problem(robot=world.robot, bases=world.bases, unloaded=a, loaded=a), Options()
        )
    bp = world.bases[WristFriction.PHYSICAL]
    da, db = (make_design(r, bp, WristFriction.PHYSICAL, world.robot) for r in (a, b))
    with pytest.raises(InputError, match="positive") as exc:
        identify_gains(da, db, world.payload, world.robot.apriori_gains, alpha=-1.0)
    assert exc.value.key == "alpha"
    with pytest.raises(InputError, match=r"\(0, 1\)") as exc:
        cross_validate([da], world.robot.apriori_gains, list(bp.names), fraction=1.0)
    assert exc.value.key == "cv_fraction"
