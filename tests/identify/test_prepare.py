"""Preparation of runs: regressor columns, base sets, chunked parallel decimation."""

from __future__ import annotations

import json

import numpy as np
import pytest

from drivegain.config.robot import WristFriction
from drivegain.dynamics.base import random_states
from drivegain.dynamics.params import standard_names
from drivegain.dynamics.regressor import stack_joint_major, standard_regressor
from drivegain.identify import prepare
from drivegain.identify.columns import coupled_coulomb_columns, regressor_columns
from drivegain.identify.loading import trajectory_bandwidth
from drivegain.identify.prepare import filtered_derivatives, five_point, prepare_recording
from drivegain.identify.signal import default_filter
from drivegain.identify.synth import model_with_friction


@pytest.mark.parametrize("form", list(WristFriction))
def test_stored_columns_equal_the_regressor_of_each_form(world, form: WristFriction) -> None:
    rng = np.random.default_rng(1)
    q, qd, qdd = random_states(world.model, 50, rng)
    names = standard_names(world.robot)
    ref = standard_regressor(world.model, q, qd, qdd, form)
    got = regressor_columns(world.model, q, qd, qdd, world.columns)
    for i, key in enumerate(world.columns):
        name, _, key_form = key.partition("@")
        if (key_form or "physical") == form.value or not name.startswith("fcm"):
            np.testing.assert_array_equal(got[:, :, i], ref[:, :, names.index(name)])
    fcm = coupled_coulomb_columns(world.robot, qd, form)
    np.testing.assert_array_equal(fcm[:, :, 0], ref[:, :, names.index("fcm6")])


@pytest.mark.parametrize("form", list(WristFriction))
def test_base_sets_reproduce_torques_and_are_minimal(world, form: WristFriction) -> None:
    bp = world.bases[form]
    model = model_with_friction(world.model, form)
    rng = np.random.default_rng(2)
    w = stack_joint_major(standard_regressor(model, *random_states(model, 150, rng)))
    chi = rng.standard_normal(w.shape[1])
    np.testing.assert_allclose(
        w[:, bp.base_index] @ bp.regroup(chi), w @ chi, atol=1e-9 * np.abs(w @ chi).max()
    )
    wb = w[:, bp.base_index]
    s = np.linalg.svd(wb / np.linalg.norm(wb, axis=0), compute_uv=False)
    assert s[-1] > 1e-6 * s[0]  # no column without torque (MZ2 of the TX-40 is not one)
    assert "MZ2" not in bp.names


@pytest.mark.parametrize(
    "limits",
    [{"CHUNK": 700, "WINDOW_PADS": 1}, {"CHUNK": 700, "WINDOW_BYTES": 1}],
    ids=["few-pads", "byte-cap"],
)
def test_chunked_decimation_equals_whole_signal(world, monkeypatch, limits) -> None:
    rate = 200.0
    t = np.arange(0.0, 60.0, 1.0 / rate)
    q, _, _ = world.excitations[0].evaluate(t)[:3]
    rng = np.random.default_rng(3)
    current = rng.normal(size=q.shape)
    st = default_filter(rate, 1.0)
    kw = dict(label="a", q=q, current=current, rate_hz=rate, settings=st)
    whole = prepare_recording(world.model, world.columns, **kw)
    for name, value in limits.items():  # windows of two filter memories, the least
        monkeypatch.setattr(prepare, name, value)
    seen = []
    chunked = prepare_recording(world.model, world.columns, progress=seen.append, **kw)
    assert len(seen) > 3 and sum(seen) == t.size
    np.testing.assert_array_equal(chunked.t, whole.t)
    scale = np.abs(whole.regressor.dense()).max(axis=(0, 1)) + 1e-300
    assert np.max(np.abs(chunked.regressor.dense() - whole.regressor.dense()) / scale) < 1e-9
    np.testing.assert_allclose(chunked.current, whole.current, atol=1e-9)


def test_decimated_regressor_follows_the_trajectory(world) -> None:
    """Low-frequency content passes the filters: decimated W ≈ W of the exact states.

    Up to the pass-band ripple of the decimation filter (Chebyshev I, 0.05 dB, applied forward
    and backward: about 1 %), which Y gets too; a one-sample shift would be a 25 % error here.
    """
    rate = 250.0
    t = np.arange(0.0, 20.0, 1.0 / rate)
    ex = world.excitations[1]
    q, _, _ = ex.evaluate(t)[:3]
    st = default_filter(rate, 1.0)
    run = prepare_recording(
        world.model,
        world.columns,
        label="a",
        q=q,
        current=np.zeros_like(q),
        rate_hz=rate,
        settings=st,
    )
    qe, qde, qdde = ex.evaluate(run.t)[:3]
    exact = regressor_columns(world.model, qe, qde, qdde, world.columns)
    # Friction sign columns switch sharply and are smoothed by the filters: compare the rest.
    smooth = [i for i, k in enumerate(world.columns) if not k.startswith(("Fc", "fcm"))]
    err = np.abs(run.regressor.dense()[:, :, smooth] - exact[:, :, smooth]).max()
    assert err < 0.015 * np.abs(exact[:, :, smooth]).max()


def test_trajectory_bandwidth_from_attachment() -> None:
    traj = {
        "fourier": {
            "base_frequency_hz": 0.1,
            "q0": [0.0] * 6,
            "a": [[0.1] * 5] * 6,
            "b": [[0.0] * 5] * 6,
        }
    }
    att = {"robot.toml": b"[robot]\n", "traj.json": json.dumps(traj).encode()}
    assert trajectory_bandwidth(att) == pytest.approx(0.5)
    assert trajectory_bandwidth({"x.json": b"{not json"}) is None


def test_filtered_derivatives_are_unbiased_at_low_sample_rates() -> None:
    """Five-point differences: a 1 Hz harmonic sampled at 250 Hz keeps its amplitude to 1e-7
    (three-point differences lose 5e-5 on the acceleration, enough to bias the gains)."""
    rate = 250.0
    t = np.arange(0.0, 20.0, 1.0 / rate)
    w = 2 * np.pi * 1.0
    q = np.column_stack([np.sin(w * t), 0.3 * np.cos(0.2 * w * t)])
    st = default_filter(rate, 1.0)
    _, qd, qdd = filtered_derivatives(q, rate, st)
    inner = slice(500, -500)
    qd_ref = np.column_stack([w * np.cos(w * t), -0.06 * w * np.sin(0.2 * w * t)])
    qdd_ref = np.column_stack([-(w**2) * np.sin(w * t), -0.012 * w**2 * np.cos(0.2 * w * t)])
    assert np.abs(qd[inner] - qd_ref[inner]).max() < 1e-7 * w
    assert np.abs(qdd[inner] - qdd_ref[inner]).max() < 1e-7 * w**2


def test_decimation_stage_equals_scipy_decimate() -> None:
    """The cached filter design gives scipy.signal.decimate's output exactly."""
    import scipy.signal as sps

    from drivegain.identify.decimate import MAX_STAGE, _decimate_stage

    rng = np.random.default_rng(0)
    x = rng.normal(size=(3000, 3)).cumsum(axis=0)
    for q in (2, 5, MAX_STAGE):
        expected = sps.decimate(x, q, ftype="iir", axis=0, zero_phase=True)
        np.testing.assert_array_equal(_decimate_stage(x, q), expected)


def test_five_point_windows_equal_the_whole_run_stencils() -> None:
    rng = np.random.default_rng(8)
    qf, rate = rng.standard_normal((1000, 3)), 250.0
    h = 1.0 / rate
    qd = np.empty_like(qf)
    qdd = np.empty_like(qf)
    qd[2:-2] = (qf[:-4] - 8.0 * qf[1:-3] + 8.0 * qf[3:-1] - qf[4:]) / (12.0 * h)
    qdd[2:-2] = (-qf[:-4] + 16.0 * qf[1:-3] - 30.0 * qf[2:-2] + 16.0 * qf[3:-1] - qf[4:]) / (
        12.0 * h * h
    )
    for d in (qd, qdd):  # the two samples at each end repeat their neighbours
        d[:2], d[-2:] = d[2], d[-3]
    for start, stop in [(0, 1000), (0, 1), (1, 7), (500, 613), (995, 1000), (990, 5000)]:
        got_qd, got_qdd = five_point(qf, rate, start, stop)
        np.testing.assert_array_equal(got_qd, qd[start:stop])
        np.testing.assert_array_equal(got_qdd, qdd[start:stop])


def test_repeated_series_are_filtered_once_with_the_same_numbers(world, monkeypatch) -> None:
    rate = 200.0
    t = np.arange(0.0, 30.0, 1.0 / rate)
    q, _, _ = world.excitations[0].evaluate(t)[:3]
    current = np.random.default_rng(4).normal(size=q.shape)
    kw = dict(label="a", q=q, current=current, rate_hz=rate, settings=default_filter(rate, 1.0))
    filtered: list[int] = []
    decimate = prepare.decimate_columns

    def counting(x, factor, same_as=None, **k):
        out = decimate(x, factor, same_as, **k)
        filtered.append(x.shape[1] - int(np.sum(same_as != np.arange(x.shape[1]))))
        return out

    monkeypatch.setattr(prepare, "decimate_columns", counting)
    shared = prepare_recording(world.model, world.columns, **kw)
    assert filtered and filtered[0] < shared.regressor.series.shape[1]  # some repeat
    # every series filtered on its own: bit for bit the same run
    monkeypatch.setattr(prepare, "first_equal", lambda v: np.arange(v.shape[1]))
    alone = prepare_recording(world.model, world.columns, **kw)
    np.testing.assert_array_equal(shared.regressor.series, alone.regressor.series)
    np.testing.assert_array_equal(shared.current, alone.current)
    np.testing.assert_array_equal(shared.reversal_share, alone.reversal_share)
