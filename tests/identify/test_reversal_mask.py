"""The reversal mask (``identify --reversal-mask``, ``reversals.reversal_mask``).

Checked against a per-sample loop for the weights, against the equation error of the true
parameters on noise-free data for the exactness of the weighted equations, and against the
whole-signal preparation for the chunked one.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from drivegain.cli import main
from drivegain.config import resource_path
from drivegain.config.robot import WristFriction, load_robot
from drivegain.dynamics.params import truth_vector
from drivegain.errors import IdentificationError, InputError
from drivegain.identify import prepare, prepchoice
from drivegain.identify.design import make_design
from drivegain.identify.maskgate import AUTO_TAPER_S, gate_note, stuck_drives
from drivegain.identify.prepare import prepare_recording
from drivegain.identify.reversals import coupled_blocks, masked_drives, reversal_mask
from drivegain.identify.signal import MAX_REVERSAL_MASK_S, FilterSettings, default_filter

from .conftest import BASE_HZ, HARMONICS, simulate_noisy

TX40 = load_robot(resource_path("tx40.toml"))


def _loop_mask(zones: np.ndarray, group: np.ndarray, width: float) -> np.ndarray:
    """The weights sample by sample: distance to the nearest marked sample of the group."""
    out = np.ones_like(zones)
    for i in range(zones.shape[1]):
        marked = [k for k in range(zones.shape[0]) if zones[k, group == group[i]].any()]
        for k in range(zones.shape[0]):
            if marked:
                d = min(abs(k - m) for m in marked)
                out[k, i] = 1.0 if d >= width else 0.5 - 0.5 * math.cos(math.pi * d / width)
    return out


def test_the_coupled_wrist_is_one_group() -> None:
    np.testing.assert_array_equal(coupled_blocks(TX40), [0, 1, 2, 3, 4, 4])


def test_the_mask_is_nought_in_the_zones_and_rises_as_a_raised_cosine() -> None:
    rng = np.random.default_rng(4)
    zones = np.zeros((300, TX40.n))
    zones[40:46, 0] = 1.0  # joint 1 reverses once...
    zones[200:203, 0] = 1.0  # ...and again
    zones[100:104, 5] = 1.0  # drive 6 (the coupled motor): drives 5 and 6 alike
    zones[280:, 2] = 1.0  # a zone that runs to the end
    zones[rng.integers(0, 300, 5), 3] = 1.0  # scattered single samples
    rate, taper = 100.0, 0.13  # 13 samples
    got = reversal_mask(zones, TX40, rate, taper)
    np.testing.assert_allclose(got, _loop_mask(zones, coupled_blocks(TX40), 13.0), atol=1e-12)
    assert np.all(got[zones[:, 0] > 0, 0] == 0.0)
    np.testing.assert_array_equal(got[:, 4], got[:, 5])
    assert np.all(got[:, 1] == 1.0)  # joint 2 never reverses
    assert got[100 - 13, 4] == 1.0 and got[100 - 7, 4] < 1.0


def test_the_mask_refuses_what_it_cannot_use() -> None:
    zones = np.zeros((10, TX40.n))
    for bad in (0.0, -0.1, math.nan):
        with pytest.raises(ValueError, match="taper_s"):
            reversal_mask(zones, TX40, 100.0, bad)
    with pytest.raises(ValueError, match="rate_hz"):
        reversal_mask(zones, TX40, 0.0, 0.1)
    with pytest.raises(ValueError, match="zones"):
        reversal_mask(zones[:, :5], TX40, 100.0, 0.1)
    for bad in (0.0, -1.0, math.inf, MAX_REVERSAL_MASK_S * 2):
        with pytest.raises(InputError, match="reversal_mask"):
            FilterSettings(cutoff_hz=5.0, decimate=2, trim=1, reversal_mask_s=bad)
    assert default_filter(250.0, 0.5, reversal_mask_s=0.1).reversal_mask_s == 0.1
    assert default_filter(250.0, 0.5).reversal_mask_s is None


def test_the_mask_can_weigh_some_groups_only() -> None:
    rng = np.random.default_rng(5)
    zones = (rng.random((400, TX40.n)) < 0.02).astype(float)
    whole = reversal_mask(zones, TX40, 100.0, 0.05)
    some = reversal_mask(zones, TX40, 100.0, 0.05, drives=(5, 1))
    # drive 6's group is drives 5 and 6; drive 2 is alone; the others keep every equation
    np.testing.assert_array_equal(masked_drives(TX40, (5, 1)), [0, 1, 0, 0, 1, 1])
    np.testing.assert_array_equal(some[:, [1, 4, 5]], whole[:, [1, 4, 5]])
    assert np.all(some[:, [0, 2, 3]] == 1.0) and np.any(whole[:, [0, 2, 3]] < 1.0)
    np.testing.assert_array_equal(reversal_mask(zones, TX40, 100.0, 0.05, drives=()), 1.0)
    assert masked_drives(TX40, None).all()
    with pytest.raises(ValueError, match="drives are 0 to 5"):
        reversal_mask(zones, TX40, 100.0, 0.05, drives=(6,))


@pytest.mark.parametrize(
    ("taper", "drives", "match"),
    [
        (None, (1,), "needs reversal_mask"),
        (0.1, (), "increasing drive indices"),
        (0.1, (-1,), "increasing drive indices"),
        (0.1, (2, 1), "increasing drive indices"),
        (0.1, (1, 1), "increasing drive indices"),
        (0.1, [1], "increasing drive indices"),
        (0.1, (True,), "increasing drive indices"),
    ],
)
def test_the_settings_refuse_a_bad_choice_of_drives(taper, drives, match) -> None:
    with pytest.raises(InputError, match=match) as info:
        FilterSettings(
            cutoff_hz=5.0, decimate=2, trim=1, reversal_mask_s=taper, reversal_mask_drives=drives
        )
    assert info.value.key == "reversal_mask_drives"


def test_the_gate_picks_the_drives_whose_kappa_says_they_stick() -> None:
    assert stuck_drives(np.array([0.2, 1.0, 3.0, 0.0, 0.5, 0.99])) == (1, 2)
    assert stuck_drives(np.zeros(6)) == ()
    with pytest.raises(ValueError, match="finite"):
        stuck_drives(np.array([0.2, math.nan]))
    kappa = np.array([0.2, 0.1, 0.0, 0.3, 2.5, 0.4])
    note = gate_note(TX40, kappa, stuck_drives(kappa))
    names = TX40.joint_names
    # drive 5 sticks: its coupled group (drives 5 and 6) is weighted out, not drive 4
    assert f"{names[4]}, {names[5]} weighted out" in note and "2.5" in note
    assert f"{AUTO_TAPER_S:g} s" in note and f"{names[3]}," not in note.split("weighted")[0]
    assert "no drive sticks" in gate_note(TX40, kappa / 10, ())


@pytest.fixture(scope="module")
def clean_runs(world):
    """Runs a and b of the exact tracking without noise or encoder quantum, 250 Hz."""
    t = np.arange(0.0, 30.0, 1.0 / 250.0)
    rng = np.random.default_rng(0)
    return [
        simulate_noisy(world, k, p, t, rng, torque_noise=0.0, quantum=0.0)
        for k, p in ((0, None), (1, world.payload))
    ]


def _prepared(world, sim, payload, mask_s, drives=None):
    st = default_filter(
        250.0, BASE_HZ * HARMONICS, reversal_mask_s=mask_s, reversal_mask_drives=drives
    )
    return prepare_recording(
        world.model,
        world.columns,
        label="run",
        q=sim.q,
        current=sim.current_reference,
        rate_hz=250.0,
        settings=st,
        payload=payload,
    )


def test_the_masked_equations_stay_exact(world, clean_runs) -> None:
    """Both sides weighted alike before the (linear) filters: with the true parameters the
    weighted equations hold as well as the plain ones, to the filters' own error (a weight on
    one side only, or shifted, would leave the masked torque itself, ~1 of it)."""
    bp = world.bases[WristFriction.PHYSICAL]
    chi = bp.regroup(truth_vector(world.robot, world.truth))
    g = world.truth.gains
    rel = {}
    for mask_s in (None, 0.1):
        err, ref = [], []
        for sim, payload in zip(clean_runs, (None, world.payload), strict=True):
            run = _prepared(world, sim, payload, mask_s)
            if mask_s is not None:
                assert run.reversal_coulomb.size == 0  # no zone left to fit
                assert not np.any(run.reversal_share)
            d = make_design(run, bp, WristFriction.PHYSICAL, world.robot)
            y = d.torque(g)
            err.append(y - d.model_torque(chi, None if payload is None else payload.values))
            ref.append(y)
        e, y = np.vstack(err), np.vstack(ref)
        rel[mask_s] = np.sqrt(np.mean(e**2, axis=0) / np.mean(y**2, axis=0))
    print(f"\nrelative equation error per joint: plain {rel[None]}, masked {rel[0.1]}")
    assert np.all(rel[None] < 1e-5) and np.all(rel[0.1] < 1e-5)


def test_a_mask_on_some_drives_leaves_the_others_their_reversal_terms(world, clean_runs) -> None:
    """The mask on drive 5's group only: drives 5 and 6 lose their shares near reversals and
    the reversal Coulomb columns of the velocities that reach only them (j5, j6, motor 6);
    drives 1-4 keep theirs, and the equations still hold with the true parameters."""
    bp = world.bases[WristFriction.PHYSICAL]
    chi = bp.regroup(truth_vector(world.robot, world.truth))
    plain = _prepared(world, clean_runs[1], world.payload, None)
    some = _prepared(world, clean_runs[1], world.payload, 0.1, drives=(4,))
    np.testing.assert_array_equal(some.reversal_share[:, 4:], 0.0)
    np.testing.assert_array_equal(some.reversal_share[:, :4], plain.reversal_share[:, :4])
    assert np.any(plain.reversal_share[:, 4:])
    first = len(plain.columns)
    kept = {int(c) - first for c in some.reversal_coulomb}
    assert kept == {int(c) - first for c in plain.reversal_coulomb} - {4, 5, 6}
    assert kept  # the first four joints' columns are still there
    np.testing.assert_array_equal(some.current[:, :4], plain.current[:, :4])
    assert np.any(np.abs(some.current[:, 4:] - plain.current[:, 4:]) > 1e-3)
    d = make_design(some, bp, WristFriction.PHYSICAL, world.robot)
    y = d.torque(world.truth.gains)
    e = y - d.model_torque(chi, world.payload.values)
    assert np.all(np.sqrt(np.mean(e**2, axis=0) / np.mean(y**2, axis=0)) < 1e-5)


def test_the_masked_preparation_is_the_same_in_chunks(world, clean_runs, monkeypatch) -> None:
    whole = _prepared(world, clean_runs[0], None, 0.08)
    monkeypatch.setattr(prepare, "CHUNK", 700)
    monkeypatch.setattr(prepare, "WINDOW_PADS", 1)
    chunked = _prepared(world, clean_runs[0], None, 0.08)
    np.testing.assert_array_equal(chunked.t, whole.t)
    scale = np.abs(whole.regressor.dense()).max(axis=(0, 1)) + 1e-300
    assert np.max(np.abs(chunked.regressor.dense() - whole.regressor.dense()) / scale) < 1e-9
    np.testing.assert_allclose(chunked.current, whole.current, atol=1e-9)
    plain = _prepared(world, clean_runs[0], None, None)
    assert np.any(np.abs(plain.current - whole.current) > 1e-3 * np.abs(plain.current).max())


def _identify_argv(logs: dict) -> list[str]:
    argv = ["identify", "--robot", str(resource_path("tx40.toml")), "--unloaded", str(logs["a"])]
    argv += ["--loaded", str(logs["b"])]
    return [*argv, "--payload", str(resource_path("payloads/calibrated-4590g.toml")), "--no-plots"]


def test_identify_takes_the_mask_and_records_it(world, run_logs, tmp_path, capsys) -> None:
    """End to end through ``drivegain identify``: every run's filter records the taper, and on
    exact tracking (nothing sticks) the masked gains keep the truth within their σ."""
    logs = run_logs(tmp_path, {"a": 7, "b": 8}, seconds=12.0)
    argv = _identify_argv(logs)
    for bad in ("-0.1", "nan"):
        assert main([*argv, "--out", str(tmp_path / "bad"), "--reversal-mask", bad]) == 2
    assert main([*argv, "--out", str(tmp_path / "bad"), "--reversal-mask", "5"]) == 2
    err = capsys.readouterr().err
    assert "--reversal-mask" in err and "at most 1" in err and "Traceback" not in err
    assert not (tmp_path / "bad").exists()
    out = tmp_path / "masked"
    assert main([*argv, "--out", str(out), "--reversal-mask", "0.1"]) == 0
    doc = json.loads((out / "report.json").read_text())
    assert [r["filter"]["reversal_mask_s"] for r in doc["runs"]] == [0.1, 0.1]
    g = np.array([x["value"] for x in doc["gains"]])
    s = np.array([x["std"] for x in doc["gains"]])
    z = (g - world.truth.gains) / s
    assert np.all(np.abs(z) < 4.0), z
    plain = tmp_path / "plain"
    assert main([*argv, "--out", str(plain)]) == 0
    doc = json.loads((plain / "report.json").read_text())
    assert [r["filter"]["reversal_mask_s"] for r in doc["runs"]] == [None, None]
    assert [r["filter"]["reversal_mask_drives"] for r in doc["runs"]] == [None, None]


def test_identify_auto_masks_only_where_a_drive_sticks(
    world, run_logs, tmp_path, capsys, monkeypatch
) -> None:
    """``--reversal-mask auto`` through ``drivegain identify``: on exact tracking no drive
    sticks, so nothing is masked and the runs say why; when the gate picks drive 5 the runs are
    prepared again with the mask on its group, recorded per run. Without a loaded run there is
    no fit to choose from: exit 2, nothing written."""
    logs = run_logs(tmp_path, {"a": 7, "b": 8}, seconds=12.0)
    argv = _identify_argv(logs)
    bad = tmp_path / "bad"
    alone = ["identify", "--robot", "tx40", "--unloaded", str(logs["a"]), "--out", str(bad)]
    assert main([*alone, "--reversal-mask", "auto", "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert "--reversal-mask" in err and "--loaded" in err and "Traceback" not in err
    assert not bad.exists()
    assert main([*argv, "--out", str(bad), "--reversal-mask", "sometimes"]) == 2
    assert "--reversal-mask" in capsys.readouterr().err and not bad.exists()
    out = tmp_path / "auto"
    assert main([*argv, "--out", str(out), "--reversal-mask", "auto"]) == 0
    doc = json.loads((out / "report.json").read_text())
    assert [r["filter"]["reversal_mask_s"] for r in doc["runs"]] == [None, None]
    assert all(any("no drive sticks" in n for n in r["notes"]) for r in doc["runs"])
    monkeypatch.setattr(prepchoice, "stuck_drives", lambda kappa: (4,))
    forced = tmp_path / "forced"
    assert main([*argv, "--out", str(forced), "--reversal-mask", "auto"]) == 0
    doc = json.loads((forced / "report.json").read_text())
    assert [r["filter"]["reversal_mask_s"] for r in doc["runs"]] == [AUTO_TAPER_S] * 2
    assert [r["filter"]["reversal_mask_drives"] for r in doc["runs"]] == [[5], [5]]
    assert all(any("weighted out" in n for n in r["notes"]) for r in doc["runs"])
    g = np.array([x["value"] for x in doc["gains"]])
    s = np.array([x["std"] for x in doc["gains"]])
    assert np.all(np.abs((g - world.truth.gains) / s) < 4.0)


def test_identify_auto_goes_on_unmasked_when_its_own_fit_fails(
    run_logs, tmp_path, monkeypatch
) -> None:
    """With no fit from the sign's choice the gate fits runs a and b itself; when that fails
    it masks nothing and says so, and the procedure goes on (its own fit decides)."""
    logs = run_logs(tmp_path, {"a": 7, "b": 8}, seconds=12.0)
    choose = prepchoice.sign_choice

    def without_fit(*a, **kw):
        loaded, _, at_cutoff = choose(*a, **kw)
        return loaded, None, at_cutoff

    def fails(*a, **kw):
        raise IdentificationError("the runs do not determine the unknowns")

    monkeypatch.setattr(prepchoice, "sign_choice", without_fit)
    monkeypatch.setattr(prepchoice, "ml_fit", fails)
    out = tmp_path / "out"
    assert main([*_identify_argv(logs), "--out", str(out), "--reversal-mask", "auto"]) == 0
    doc = json.loads((out / "report.json").read_text())
    assert [r["filter"]["reversal_mask_s"] for r in doc["runs"]] == [None, None]
    note = "reversal mask (auto): not chosen, the unmasked fit failed"
    assert all(any(note in n for n in r["notes"]) for r in doc["runs"])
