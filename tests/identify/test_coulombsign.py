"""The Coulomb sign's cut-off, lowered where the encoder is coarse (identify/coulombsign.py).

The noise gain is checked against white noise put through the shipped filter and differences,
the quantisation model against a coarsely read smooth motion, and the rule against what it is
for: a sign that changes only where the motion reverses.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from drivegain.cli import main
from drivegain.config import resource_path
from drivegain.errors import InputError
from drivegain.identify.coulombsign import (
    SIGN_QUANTUM_NOISE,
    encoder_steps,
    quantum_noise,
    sign_cutoff,
    velocity_noise_gain,
)
from drivegain.identify.prepare import filtered_derivatives, prepare_recording
from drivegain.identify.signal import FilterSettings, default_filter

from .conftest import BASE_HZ, HARMONICS, simulate_noisy

RATE_HZ = 250.0


def _velocity(q: np.ndarray, cutoff_hz: float) -> np.ndarray:
    """The shipped velocity of ``q`` (N, n) at ``cutoff_hz``: filter, five-point differences."""
    return filtered_derivatives(
        q, RATE_HZ, FilterSettings(cutoff_hz=cutoff_hz, decimate=1, trim=0)
    )[1]


@pytest.mark.parametrize("cutoff_hz", [5.0, 40.0, 100.0])
def test_the_noise_gain_is_that_of_white_noise_through_the_velocitys_filters(cutoff_hz) -> None:
    x = np.random.default_rng(3).standard_normal((400_000, 1))
    v = _velocity(x, cutoff_hz)[2000:-2000]
    assert v.std() == pytest.approx(velocity_noise_gain(RATE_HZ, cutoff_hz, 4), rel=0.03)


def _smooth_motion(t: np.ndarray) -> np.ndarray:
    w = 2 * np.pi * np.array([0.3, 0.7])
    return (0.8 * np.sin(w[0] * t) + 0.3 * np.sin(w[1] * t + 1.0))[:, None]


@pytest.mark.parametrize("cutoff_hz", [5.0, 20.0, 40.0])
def test_the_quantum_noise_model_predicts_a_coarse_encoders_velocity_error(cutoff_hz) -> None:
    t = np.arange(0.0, 120.0, 1.0 / RATE_HZ)
    q = _smooth_motion(t)
    step = float(np.deg2rad(1e-3))
    read = step * np.round(q / step + 0.37)  # an encoder whose grid does not start at 0
    exact = _velocity(q, cutoff_hz)[500:-500]
    error = _velocity(read, cutoff_hz)[500:-500] - exact
    speed = np.sqrt(np.mean(exact**2, axis=0))
    predicted = quantum_noise(np.array([step]), speed, RATE_HZ, cutoff_hz, 4)
    measured = np.sqrt(np.mean(error**2, axis=0)) / speed
    np.testing.assert_allclose(measured, predicted, rtol=0.15)


def test_encoder_steps_are_read_from_the_positions() -> None:
    t = np.arange(0.0, 20.0, 1.0 / RATE_HZ)
    q = _smooth_motion(t)
    step = float(np.deg2rad(2e-3))
    read = step * np.round(q / step)
    got = encoder_steps(np.column_stack([read, q, np.full_like(q, 0.3)]))
    assert got[0] == pytest.approx(step, rel=1e-9)
    assert got[1] == 0.0  # unquantised: no lattice
    assert got[2] == 0.0  # never moves
    with pytest.raises(ValueError, match="shape"):
        encoder_steps(q[:, 0])


def test_the_sign_cutoff_is_halved_until_the_noise_fits() -> None:
    speed = np.array([1.0, 1.0])
    steps = np.array([1e-7, 0.0])

    def noise(hz: float) -> float:
        return float(quantum_noise(steps, speed, RATE_HZ, hz, 4)[0])

    # a step whose noise fits at 20 Hz, not at 40 Hz
    step = 0.5 * (SIGN_QUANTUM_NOISE / noise(40.0) + SIGN_QUANTUM_NOISE / noise(20.0)) * 1e-7
    got = sign_cutoff(40.0, 5.0, RATE_HZ, 4, np.array([step, 0.0]), speed)
    assert got == 20.0
    assert sign_cutoff(40.0, 5.0, RATE_HZ, 4, np.array([step / 100, 0.0]), speed) == 40.0
    assert sign_cutoff(40.0, 5.0, RATE_HZ, 4, np.array([step * 1e4, 0.0]), speed) == 5.0
    # a drive that does not move does not lower it
    assert sign_cutoff(40.0, 5.0, RATE_HZ, 4, np.array([step * 1e4, 0.0]), np.zeros(2)) == 40.0
    with pytest.raises(InputError, match="sign_noise_limit"):
        sign_cutoff(40.0, 5.0, RATE_HZ, 4, steps, speed, limit=0.0)
    with pytest.raises(InputError, match="sign_noise_limit"):
        FilterSettings(cutoff_hz=5.0, decimate=2, trim=1, sign_noise_limit=-1.0)


def _reversals(v: np.ndarray) -> np.ndarray:
    """Sign changes per column of velocities ``v`` (N, n)."""
    s = np.sign(v)
    return np.array([np.count_nonzero(np.diff(c[c != 0]) != 0) for c in s.T])


@pytest.mark.parametrize("quantum_deg", [1e-2, 1e-5])
def test_the_default_sign_changes_only_where_the_motion_reverses(world, quantum_deg) -> None:
    """A coarse encoder (1e-2° at the joint) makes the velocity at 8 × the position cut-off
    (80 Hz) change sign around the reversals; the default lowers the cut-off until it does not,
    and keeps it where the encoder is fine (1e-5°). A cut-off given by hand is used as given."""
    t = np.arange(0.0, 20.0, 1.0 / RATE_HZ)
    quantum = float(np.deg2rad(quantum_deg))
    sim = simulate_noisy(world, 0, None, t, np.random.default_rng(11), quantum=quantum)
    qd_true = world.excitations[0].evaluate(t)[1]
    auto = default_filter(RATE_HZ, BASE_HZ * HARMONICS)
    given = default_filter(RATE_HZ, BASE_HZ * HARMONICS, sign_cutoff_hz=auto.sign_cutoff)
    assert auto.sign_noise_limit == SIGN_QUANTUM_NOISE and given.sign_noise_limit is None

    def prepared(settings: FilterSettings) -> FilterSettings:
        run = prepare_recording(
            world.model,
            world.columns,
            label="a",
            q=sim.q,
            current=sim.current_reference,
            rate_hz=RATE_HZ,
            settings=settings,
        )
        assert run.filter is not None
        return run.filter

    chosen = prepared(auto).sign_cutoff
    assert prepared(given).sign_cutoff == auto.sign_cutoff
    inner = slice(250, -250)  # the filters' borders
    true_reversals = _reversals(qd_true[inner])
    at_ceiling = _reversals(_velocity(sim.q, auto.sign_cutoff)[inner])
    at_chosen = _reversals(_velocity(sim.q, chosen)[inner])
    if quantum_deg > 1e-3:
        assert chosen < auto.sign_cutoff
        assert np.any(at_ceiling > true_reversals)  # the premise: a flickering sign
    else:
        assert chosen == auto.sign_cutoff
    np.testing.assert_array_equal(at_chosen, true_reversals)


def test_the_report_says_when_the_sign_cutoff_came_down(run_logs, tmp_path) -> None:
    """End to end through ``drivegain identify``: logs of a coarse encoder (1e-2° at the joint)
    get a lower sign cut-off than 8 × the position cut-off, the report records it, the limit
    and a note per run."""
    logs = run_logs(tmp_path, {"a": 3, "b": 4}, seconds=12.0, quantum=float(np.deg2rad(1e-2)))
    out = tmp_path / "report"
    argv = ["identify", "--robot", str(resource_path("tx40.toml")), "--unloaded", str(logs["a"])]
    argv += ["--loaded", str(logs["b"])]
    argv += ["--payload", str(resource_path("payloads/calibrated-4590g.toml")), "--out", str(out)]
    assert main([*argv, "--no-plots"]) == 0
    runs = json.loads((out / "report.json").read_text())["runs"]
    assert len(runs) == 2
    for run in runs:
        f = run["filter"]
        assert f["sign_noise_limit"] == SIGN_QUANTUM_NOISE
        assert f["cutoff_hz"] <= f["sign_cutoff_hz"] < 8 * f["cutoff_hz"]
        assert any(n.startswith("Coulomb sign's velocity filtered at") for n in run["notes"])


def test_the_report_says_which_sign_the_runs_likelihood_chose(run_logs, tmp_path) -> None:
    """End to end through ``drivegain identify``: where the rule keeps the sign above the
    position cut-off (a 1e-3° encoder), the runs are prepared with the sign at the position
    cut-off too and the likelier preparation is kept (identify.signchoice); each run's note names
    the cut-off kept, the one its filter records. A cut-off given by hand: no rule, no choice."""
    logs = run_logs(tmp_path, {"a": 5, "b": 6}, seconds=12.0)
    out = tmp_path / "report"
    argv = ["identify", "--robot", str(resource_path("tx40.toml")), "--unloaded", str(logs["a"])]
    argv += ["--loaded", str(logs["b"])]
    argv += ["--payload", str(resource_path("payloads/calibrated-4590g.toml")), "--no-plots"]
    assert main([*argv, "--out", str(out)]) == 0
    runs = json.loads((out / "report.json").read_text())["runs"]
    kept = set()
    for run in runs:
        f = run["filter"]
        chosen = [n for n in run["notes"] if "chosen by the runs' likelihood" in n]
        assert len(chosen) == 1, run["notes"]
        assert chosen[0].startswith(
            f"Coulomb sign's velocity filtered at {f['sign_cutoff_hz']:g} Hz"
        )
        assert "(−2 log L larger by" in chosen[0] or "(the same likelihood)" in chosen[0]
        other = f["cutoff_hz"] if f["sign_cutoff_hz"] > f["cutoff_hz"] else 8 * f["cutoff_hz"]
        assert f" over {other:g} Hz " in chosen[0]
        kept.add(f["sign_cutoff_hz"])
    assert len(kept) == 1  # one preparation for all runs
    given = tmp_path / "given"
    assert main([*argv, "--out", str(given), "--sign-cutoff", "12"]) == 0
    for run in json.loads((given / "report.json").read_text())["runs"]:
        assert run["filter"]["sign_cutoff_hz"] == 12.0
        assert run["filter"]["sign_noise_limit"] is None
        assert not any("Coulomb sign" in n for n in run["notes"])
