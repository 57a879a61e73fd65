"""``drivegain convert csv``: transmission conversions checked against the TX-40's explicit
formulas (README of the real data), the real recording, and one-line errors with nothing
written."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from drivegain.cli import main
from drivegain.config import load_robot, resource_path
from drivegain.dynamics.transmission import joint_to_motor, joint_torque
from drivegain.errors import DataError, InputError
from drivegain.formats import logwriter as logformat
from drivegain.formats.logreader import read_run
from drivegain.identify.convert import convert_csv, read_csv_columns
from drivegain.identify.signal import default_filter, derivatives

ROBOT = resource_path("tx40.toml")
N = np.array([32.0, 32.0, 45.0, -48.0, 45.0, 32.0])  # gear ratios of the TX-40
HEADER = "Joint_1,Joint_2,Joint_3,Joint_4,Joint_5,Joint_6"


def tx40_motor_to_joint(qm: np.ndarray) -> np.ndarray:
    """q = K⁻¹ q_m written out: motor 6 turns with N6·(q5 + q6)."""
    q = qm / N
    q[:, 5] = qm[:, 5] / N[5] - q[:, 4]
    return q


def tx40_joint_torque(tau_m: np.ndarray) -> np.ndarray:
    """tau = Kᵀ tau_m written out: tau5 = N5 tau_m5 + N6 tau_m6, tau6 = N6 tau_m6."""
    tau = tau_m * N
    tau[:, 4] += N[5] * tau_m[:, 5]
    return tau


def write_csv(path: Path, values: np.ndarray, header: str | None = HEADER) -> Path:
    lines = [header] if header is not None else []
    lines += [",".join(repr(float(v)) for v in row) for row in values]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture()
def motor_data(tmp_path: Path) -> tuple[Path, Path, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(7)
    qm = np.cumsum(rng.normal(size=(400, 6)), axis=0) * 0.01 * N
    tau_m = rng.normal(size=(400, 6)) * 0.3
    return write_csv(tmp_path / "p.csv", qm), write_csv(tmp_path / "c.csv", tau_m), qm, tau_m


def test_motor_side_torques(tmp_path: Path, motor_data) -> None:
    pos, cur, qm, tau_m = motor_data
    out = convert_csv(
        pos, cur, 1000.0, ROBOT, motor_side=True, torque=True, out=tmp_path / "r.mcap"
    )
    assert out == tmp_path / "r.mcap" and not (tmp_path / "r.mcap.part").exists()
    log = read_run(out, n_joints=6)
    np.testing.assert_allclose(log.position, tx40_motor_to_joint(qm), rtol=1e-13, atol=1e-13)
    np.testing.assert_array_equal(log.current_reference, tau_m)  # v = motor torque
    robot = load_robot(ROBOT)
    # the contract: V(current_reference) @ gains = joint torque, with gains = gear ratios
    np.testing.assert_allclose(
        joint_torque(robot, log.current_reference, N), tx40_joint_torque(tau_m), rtol=1e-13
    )
    np.testing.assert_allclose(joint_to_motor(robot, log.position), qm, rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(log.t, np.arange(400) / 1000.0, rtol=0, atol=1e-15)
    assert log.sync_period_s == 0.001
    assert log.meta["current_unit"] == "N·m motor torque"
    assert log.meta["gains_hint"] == "gear_ratio"
    assert log.meta["robot"] == "Staubli TX-40" and log.meta["payload"] == "none"
    assert log.attachments == {ROBOT.name: ROBOT.read_bytes()}
    assert np.isnan(log.current).all() and np.isnan(log.setpoint).all()
    assert np.all(np.diff(log.log_time_ns) == 1_000_000)


def test_joint_side_torques_become_motor_torques(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    q = rng.normal(size=(100, 6))
    tau = rng.normal(size=(100, 6)) * 20
    pos, cur = write_csv(tmp_path / "q.csv", q), write_csv(tmp_path / "tau.csv", tau)
    out = convert_csv(
        pos, cur, 250.0, ROBOT, motor_side=False, torque=True, out=tmp_path / "j.mcap"
    )
    log = read_run(out)
    np.testing.assert_array_equal(log.position, q)
    np.testing.assert_allclose(tx40_joint_torque(log.current_reference), tau, rtol=1e-12)


def test_currents_are_stored_as_they_are(tmp_path: Path) -> None:
    rng = np.random.default_rng(9)
    q, amps = rng.normal(size=(60, 6)), rng.normal(size=(60, 6))
    pos = write_csv(tmp_path / "q.csv", q, header=None)  # no header row
    cur = tmp_path / "a.csv"
    cur.write_text(
        "i1;i2;i3;i4;i5;i6\n" + "\n".join(";".join(repr(float(v)) for v in r) for r in amps)
    )
    payload = resource_path("payloads/calibrated-4590g.toml")
    out = convert_csv(
        pos,
        cur,
        500.0,
        ROBOT,
        motor_side=False,
        torque=False,
        run="loaded",
        out=tmp_path / "a.mcap",
        payload=payload,
    )
    log = read_run(out)
    np.testing.assert_array_equal(log.current_reference, amps)
    assert log.meta["current_unit"] == "A" and "gains_hint" not in log.meta
    assert log.meta["run"] == "loaded" and log.meta["payload"] == "calibrated-4590g"
    assert log.attachments[payload.name] == payload.read_bytes()


def test_real_tx40_recording(tmp_path: Path, tx40_real: Path) -> None:
    out = tmp_path / "real.mcap"
    pos, cur = tx40_real / "pos_read_data.csv", tx40_real / "curr_data.csv"
    args = ["convert", "csv", "--positions", str(pos), "--currents", str(cur), "--rate", "5000"]
    args += ["--motor-side", "--torque", "--robot", str(ROBOT), "--out", str(out)]
    assert main(args) == 0
    log = read_run(out, n_joints=6)
    assert log.messages_recovered == 45_000 and not log.truncated
    assert log.t[-1] == pytest.approx(8.9998)
    _, qm = read_csv_columns(pos, 6)
    _, tau_m = read_csv_columns(cur, 6)
    np.testing.assert_allclose(log.position, tx40_motor_to_joint(qm), rtol=1e-12, atol=1e-15)
    # round trip motor -> joint -> motor
    robot = load_robot(ROBOT)
    np.testing.assert_allclose(joint_to_motor(robot, log.position), qm, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(
        joint_torque(robot, log.current_reference, N), tx40_joint_torque(tau_m), rtol=1e-12
    )
    # the data README: joint speeds peak at about 5.2, 5.2, 7.1, 7.3, 5.8, 11.9 rad/s
    _, qd, _ = derivatives(log.position, log.rate_hz, default_filter(log.rate_hz))
    peaks = np.abs(qd).max(axis=0)
    np.testing.assert_allclose(peaks, [5.2, 5.2, 7.1, 7.3, 5.8, 11.9], rtol=0.05)


# --- bad input: one line, file + line + column, nothing written -------------------------------


@pytest.mark.parametrize(
    ("positions", "currents", "fragments"),
    [
        ("1,2,3,4,5,6\n1,2,3,4,5\n", None, ["p.csv", "line 2", "5 fields, expected 6"]),
        (
            "1,2,3,4,5,6\n1,2,x3,4,5,6\n",
            None,
            ["p.csv", "line 2", "column 3", "'x3' is not a number"],
        ),
        (
            HEADER + "\n1,2,3,4,nan,6\n",
            None,
            ["p.csv", "line 2", "column 5 (Joint_5)", "not finite"],
        ),
        (HEADER + "\n1,2,3,4,5,inf\n", None, ["p.csv", "line 2", "column 6", "not finite"]),
        ("a,b,c\n1,2,3\n", None, ["p.csv", "line 1", "header has 3 columns, expected 6"]),
        ("1,2,3,4,5,6,7\n", None, ["p.csv", "line 1", "7 fields, expected 6"]),
        ("1,2,3,4,5,6\n\n1,2,3,4,5,6\n", None, ["p.csv", "line 2", "empty line"]),
        ("", None, ["p.csv", "empty file"]),
        (HEADER + "\n", None, ["p.csv", "no data rows"]),
        ("1,2,3,4,5,6\n1,2,3,4,5,6\n", "1,2,3,4,5,6\n", ["p.csv", "2 rows", "c.csv has 1"]),
        ("1,2,3,4,5,6\n", "1,2,3,4,5,6\n", ["p.csv", "at least 2 samples"]),
    ],
)
def test_bad_csv(
    tmp_path: Path, positions: str, currents: str | None, fragments: list[str]
) -> None:
    pos = tmp_path / "p.csv"
    pos.write_text(positions)
    cur = tmp_path / "c.csv"
    cur.write_text(currents if currents is not None else "1,2,3,4,5,6\n" * 2)
    out = tmp_path / "out" / "r.mcap"
    out.parent.mkdir()
    with pytest.raises(DataError) as exc:
        convert_csv(pos, cur, 100.0, ROBOT, motor_side=True, torque=True, out=out)
    text = str(exc.value)
    assert "\n" not in text
    for f in fragments:
        assert f in text, text
    assert list(out.parent.iterdir()) == []


def test_bad_options(tmp_path: Path, motor_data) -> None:
    pos, cur, _, _ = motor_data
    with pytest.raises(InputError, match="--rate"):
        convert_csv(pos, cur, 0.0, ROBOT, motor_side=True, torque=True, out=tmp_path / "x.mcap")
    with pytest.raises(InputError, match="output folder does not exist"):
        convert_csv(
            pos, cur, 10.0, ROBOT, motor_side=True, torque=True, out=tmp_path / "no" / "x.mcap"
        )
    with pytest.raises(DataError, match=r"missing\.csv: file not found"):
        convert_csv(
            tmp_path / "missing.csv",
            cur,
            10.0,
            ROBOT,
            motor_side=True,
            torque=True,
            out=tmp_path / "x.mcap",
        )
    assert not (tmp_path / "x.mcap").exists()


def test_failure_while_writing_leaves_nothing(tmp_path: Path, motor_data, monkeypatch) -> None:
    pos, cur, _, _ = motor_data
    calls = {"n": 0}
    real = logformat.LogWriter.write_joint_state

    def failing(self, **kw):
        calls["n"] += 1
        if calls["n"] == 150:
            raise OSError(28, "No space left on device")
        real(self, **kw)

    monkeypatch.setattr(logformat.LogWriter, "write_joint_state", failing)
    with pytest.raises(OSError, match="No space"):
        convert_csv(pos, cur, 100.0, ROBOT, motor_side=True, torque=True, out=tmp_path / "x.mcap")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.csv", "p.csv"]


def test_cli_exit_status_2_one_line(tmp_path: Path) -> None:
    pos = tmp_path / "p.csv"
    pos.write_text(HEADER + "\n1,2,3,4,5,6\n1,2,3,4,5\n")
    out = tmp_path / "r.mcap"
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "drivegain",
            "convert",
            "csv",
            "--positions",
            str(pos),
            "--currents",
            str(pos),
            "--rate",
            "100",
            "--motor-side",
            "--torque",
            "--robot",
            str(ROBOT),
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "p.csv" in lines[0] and "line 3" in lines[0]
    assert not out.exists() and not out.with_name("r.mcap.part").exists()
