"""The Coulomb columns' sign from a velocity filtered less than the other columns'
(``identify --sign-cutoff``).

A drive in closed loop dwells at each reversal, then breaks away: the position filter that the
inertial columns need (a few times the trajectory's bandwidth) blurs that, and moves the sign's
zero crossing off the friction's. The sign cut-off keeps it where it is.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from drivegain.cli import main
from drivegain.config import resource_path
from drivegain.dynamics.base import random_states
from drivegain.errors import InputError
from drivegain.identify.columns import regressor_columns
from drivegain.identify.coulombsign import SIGN_QUANTUM_NOISE
from drivegain.identify.decimate import parallel_decimate
from drivegain.identify.prepare import prepare_recording
from drivegain.identify.signal import FilterSettings, default_filter

RATE_HZ = 250.0


def _coulomb(key: str) -> bool:
    return key.startswith(("Fc", "fcm"))


@pytest.mark.parametrize("entries", ["whole", "series"])
def test_coulomb_columns_take_the_sign_velocity_and_nothing_else(world, entries: str) -> None:
    rng = np.random.default_rng(5)
    q, qd, qdd = random_states(world.model, 40, rng)
    other = rng.standard_normal(qd.shape)  # signs differ from qd's in about half the entries
    cols = world.columns
    at_qd = regressor_columns(world.model, q, qd, qdd, cols)
    at_other = regressor_columns(world.model, q, other, qdd, cols)
    coulomb = np.array([_coulomb(k) for k in cols])
    assert coulomb.sum() == 8  # Fc1-Fc6, fcm6 of both forms
    if entries == "whole":
        got = regressor_columns(world.model, q, qd, qdd, cols, sign_qd=other)
        np.testing.assert_array_equal(got[:, :, coulomb], at_other[:, :, coulomb])
        np.testing.assert_array_equal(got[:, :, ~coulomb], at_qd[:, :, ~coulomb])
        assert np.any(got[:, :, coulomb] != at_qd[:, :, coulomb])
        return
    rows, cs = np.nonzero(np.any(at_qd != 0.0, axis=0))
    got = regressor_columns(world.model, q, qd, qdd, cols, (rows, cs), sign_qd=other)
    sel = coulomb[cs]
    np.testing.assert_array_equal(got[:, sel], at_other[:, rows[sel], cs[sel]])
    np.testing.assert_array_equal(got[:, ~sel], at_qd[:, rows[~sel], cs[~sel]])


def _dwelling_motion(t: np.ndarray, dwell_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 6) and velocities of a 0.4 Hz swing that stops ``dwell_s`` at every
    reversal (a drive's stick), different amplitudes per joint."""
    amp = np.array([1.0, 0.8, 0.9, 1.2, 1.1, 1.5])
    w = 2 * np.pi * 0.4
    # Time on the swing's own clock: it stands still for dwell_s after each zero of cos(w s).
    half = np.pi / w
    k = np.floor((t + half / 2) / (half + dwell_s))  # reversals passed
    local = t + half / 2 - k * (half + dwell_s)  # time since the last reversal's dwell began
    s = np.where(local < dwell_s, k * half - half / 2, k * half - half / 2 + local - dwell_s)
    moving = local >= dwell_s
    q = amp[None, :] * np.sin(w * s)[:, None]
    qd = np.where(moving[:, None], amp[None, :] * w * np.cos(w * s)[:, None], 0.0)
    return q, qd


def test_a_higher_sign_cutoff_follows_a_dwelling_joints_friction(world) -> None:
    t = np.arange(0.0, 30.0, 1.0 / RATE_HZ)
    q, qd_true = _dwelling_motion(t, 0.06)
    kw = dict(label="a", q=q, current=np.zeros_like(q), rate_hz=RATE_HZ)
    errs = {}
    for sign_hz in (5.0, None):  # the position cut-off's, and the default (40 Hz here)
        st = default_filter(RATE_HZ, 0.5, sign_cutoff_hz=sign_hz)
        run = prepare_recording(world.model, world.columns, settings=st, **kw)
        keep = np.rint(run.t * RATE_HZ / st.decimate).astype(int)
        # What the friction does, decimated by the same filter as every column.
        truth = parallel_decimate([np.sign(qd_true)], st.decimate, 0)[0][keep]
        dense = run.regressor.dense()
        got = np.stack([dense[:, j, run.column_index([f"Fc{j + 1}"])[0]] for j in range(6)], 1)
        errs[sign_hz] = np.sqrt(np.mean((got - truth) ** 2, axis=0))
        if sign_hz is not None:
            plain = dense
        else:
            # Only the Coulomb columns changed.
            smooth = [i for i, k in enumerate(world.columns) if not _coulomb(k)]
            np.testing.assert_array_equal(dense[:, :, smooth], plain[:, :, smooth])
    # The 5 Hz filter blurs a 60 ms stop; 40 Hz resolves it.
    print(f"RMS error of the decimated Fc columns: 5 Hz {errs[5.0]}, 40 Hz {errs[None]}")
    assert np.all(errs[None] < 0.5 * errs[5.0]), (errs[5.0], errs[None])


def test_a_sign_cutoff_outside_the_band_is_refused() -> None:
    with pytest.raises(InputError, match="sign_cutoff"):
        default_filter(RATE_HZ, 0.5, sign_cutoff_hz=RATE_HZ / 2)
    with pytest.raises(InputError, match="sign_cutoff"):
        FilterSettings(cutoff_hz=5.0, decimate=2, trim=1, sign_cutoff_hz=0.0)
    # Default: eight times the position cut-off, below 0.4 of the rate, never below the cut-off.
    assert default_filter(RATE_HZ, 0.5).sign_cutoff_hz == 40.0
    assert default_filter(100.0, 0.5, cutoff_hz=8.0).sign_cutoff_hz == 40.0  # not 64
    assert default_filter(RATE_HZ, cutoff_hz=110.0).sign_cutoff_hz == 110.0
    assert default_filter(RATE_HZ, 0.5, sign_cutoff_hz=20).sign_cutoff == 20.0
    plain = FilterSettings(cutoff_hz=5.0, decimate=2, trim=1)
    assert plain.sign_cutoff_hz is None and plain.sign_cutoff == 5.0


def test_the_command_line_refuses_a_bad_sign_cutoff(tmp_path, capsys) -> None:
    args = ["identify", "--robot", str(resource_path("tx40.toml")), "--unloaded"]
    args += [str(tmp_path / "a.mcap"), "--out", str(tmp_path / "out"), "--sign-cutoff", "-3"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "--sign-cutoff" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_the_report_records_the_sign_cutoff(real_log, tmp_path) -> None:
    """End to end on the real TX-40 recording: the report states the cut-off used (default
    400 Hz: 8 × 50 Hz), and the fit is as good as with the sign of the position cut-off (the
    real arm's stops are at rest and left out: the residual moves by well under 1 %)."""
    from drivegain.identify.pipeline import IdentifyRequest, run_identify

    fits = {}
    for sign_hz in (None, 50.0):
        out = tmp_path / f"report-{sign_hz}"
        oc = run_identify(
            IdentifyRequest(
                robot=resource_path("tx40.toml"),
                unloaded=real_log,
                out=out,
                gains="gear-ratios",
                sign_cutoff=sign_hz,
                progress=False,
                plots=False,
            )
        )
        doc = json.loads((out / "report.json").read_text())
        assert doc["runs"][0]["filter"]["sign_cutoff_hz"] == (sign_hz or 400.0)
        # the encoder rule ran and kept 8 × (identify/coulombsign.py); a given cut-off skips it
        limit = doc["runs"][0]["filter"]["sign_noise_limit"]
        assert limit == (None if sign_hz else SIGN_QUANTUM_NOISE)
        fits[sign_hz] = oc.result.final.relative_error
    assert fits[None] == pytest.approx(fits[50.0], rel=0.02)
