"""``drivegain excite``: files written, same seed same file, bad input: exit 2, nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from drivegain.cli import main
from drivegain.config import resource_path

ROBOT = resource_path("tx40.toml")
PAYLOAD = resource_path("payloads/calibrated-4590g.toml")
# Small and fast: 2 harmonics, one start with few iterations.
QUICK = ["--harmonics", "2", "--budget", "0.6", "--periods", "1"]


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_same_seed_same_file_whatever_the_workers(tmp_path: Path, capsys) -> None:
    a, b, c = tmp_path / "a.json", tmp_path / "b.json", tmp_path / "c.json"
    args = ["excite", "--robot", str(ROBOT), "--payload", str(PAYLOAD), *QUICK]
    assert run([*args, "--seed", "4", "--jobs", "1", "--out", str(a)], capsys)[0] == 0
    code, _, err = run([*args, "--seed", "4", "--jobs", "2", "--out", str(b)], capsys)
    assert code == 0
    assert "median of 1 random feasible" in err
    assert a.read_bytes() == b.read_bytes()
    png = a.with_suffix(".png").read_bytes()
    assert png.startswith(b"\x89PNG\r\n\x1a\n") and len(png) > 10_000
    doc = json.loads(a.read_text())
    assert doc["metrics"]["cond"] > 0 and "wtls_cond" in doc["metrics"]
    assert len(doc["metrics"]["payload_torque_rms"]) == 6
    assert doc["optimisation"]["seed"] == 4 and doc["optimisation"]["payload"] == "calibrated-4590g"
    assert run([*args, "--seed", "5", "--jobs", "1", "--out", str(c)], capsys)[0] == 0
    assert c.read_bytes() != a.read_bytes()


def _bad(tmp_path: Path, capsys, extra: list[str], robot: Path = ROBOT, early: bool = True) -> str:
    """Run with bad input: exit 2, one error line (the only stderr line when the input is
    refused before any work), no file written."""
    out = tmp_path / "t.json"
    before = set(tmp_path.iterdir())
    code, _, err = run(["excite", "--robot", str(robot), "--out", str(out), *QUICK, *extra], capsys)
    assert code == 2, err
    lines = err.strip().splitlines()
    assert lines[-1].startswith("drivegain: error:"), err
    assert sum("error" in line for line in lines) == 1, err
    if early:
        assert len(lines) == 1, err
    assert set(tmp_path.iterdir()) == before  # nothing written, not even a temporary
    return lines[-1]


def test_start_outside_the_limits(tmp_path: Path, capsys) -> None:
    line = _bad(tmp_path, capsys, ["--start", "0,2.5,0,0,0,0"])
    assert "--start" in line and "j2 = 2.5 rad is outside" in line


def test_start_with_the_wrong_count(tmp_path: Path, capsys) -> None:
    assert "expected 6 angles" in _bad(tmp_path, capsys, ["--start", "0,0"])


def test_position_range_narrower_than_the_margins(tmp_path: Path, capsys) -> None:
    line = _bad(tmp_path, capsys, ["--position-margin", "2.2"])
    assert "joint[1].position_limits" in line and "tx40.toml" in line


def test_nan_in_the_robot_file(tmp_path: Path, capsys) -> None:
    text = ROBOT.read_text().replace("jerk_limit = 100.0", "jerk_limit = nan", 1)
    bad = tmp_path / "robot.toml"
    bad.write_text(text)
    line = _bad(tmp_path, capsys, [], robot=bad)
    assert "jerk_limit" in line and "finite" in line


def test_payload_without_nominal_parameters(tmp_path: Path, capsys) -> None:
    text = ROBOT.read_text().replace('name = "Staubli TX-40"', 'name = "Other arm"', 1)
    other = tmp_path / "robot.toml"
    other.write_text(text)
    line = _bad(tmp_path, capsys, ["--payload", str(PAYLOAD)], robot=other)
    assert "--nominal" in line


@pytest.mark.parametrize(
    ("option", "value"),
    [("--budget", "0"), ("--harmonics", "0"), ("--base-frequency", "-1"), ("--jobs", "0")],
)
def test_bad_options(tmp_path: Path, capsys, option: str, value: str) -> None:
    assert option in _bad(tmp_path, capsys, [option, value])


def test_unreachable_start_is_bad_input(tmp_path: Path, capsys, monkeypatch) -> None:
    """When the approach from --start cannot be planned inside the limits (TrajectoryError from
    the planner), the command reports it as bad input and writes nothing."""
    import drivegain.excite.commands as commands
    from drivegain.errors import TrajectoryError

    def refuse(*args, **kwargs):
        raise TrajectoryError("approach: j1 would reach 3.1 rad, beyond its upper working limit")

    monkeypatch.setattr(commands, "plan_motion", refuse)
    line = _bad(tmp_path, capsys, ["--start", "0,0,0,0,0,0"], early=False)
    assert "--start" in line and "unreachable start pose" in line and "j1 would reach" in line
