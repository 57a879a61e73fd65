"""TRAJ.json: round trip, contracts §6 fields, one-line errors on bad files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from drivegain.config import load_robot, resource_path
from drivegain.errors import DataError
from drivegain.excite.limits import ExcitationLimits
from drivegain.excite.trajectory import load_trajectory, save_trajectory, trajectory_document
from drivegain.formats.fourier import FourierTrajectory


@pytest.fixture(scope="module")
def robot():
    return load_robot(resource_path("tx40.toml"))


def make_file(robot, path: Path) -> FourierTrajectory:
    rng = np.random.default_rng(0)
    f = FourierTrajectory(
        0.1, rng.normal(size=6) * 0.1, rng.normal(size=(6, 4)), rng.normal(size=(6, 4)), 2
    )
    doc = trajectory_document(
        f, robot, {"cond": 12.5}, ExcitationLimits.from_robot(robot), extra={"note": "x"}
    )
    save_trajectory(path, doc)
    return f


def test_round_trip_is_exact(robot, tmp_path: Path) -> None:
    path = tmp_path / "t.json"
    f = make_file(robot, path)
    ex = load_trajectory(path)
    assert ex.robot == robot.name
    assert ex.joint_names == robot.joint_names
    assert ex.fourier.periods == 2
    np.testing.assert_array_equal(ex.fourier.a, f.a)
    np.testing.assert_array_equal(ex.fourier.b, f.b)
    np.testing.assert_array_equal(ex.fourier.q0, f.q0)
    assert ex.metrics == {"cond": 12.5}
    assert ex.limits is not None
    np.testing.assert_array_equal(ex.limits.upper, ExcitationLimits.from_robot(robot).upper)
    assert ex.extra["note"] == "x"
    # Contracts §6 fields, read with the plain json module.
    doc = json.loads(path.read_text())
    assert doc["format_version"] == 1
    assert set(doc["fourier"]) >= {"base_frequency_hz", "q0", "a", "b"}
    assert len(doc["fourier"]["a"]) == 6 and len(doc["fourier"]["a"][0]) == 4
    assert doc["start_state"]["qd"] == pytest.approx(f.a.sum(axis=1).tolist())
    assert [p.name for p in tmp_path.iterdir()] == ["t.json"]  # no temporary left


def _corrupt(robot, tmp_path: Path, edit) -> Path:
    path = tmp_path / "t.json"
    make_file(robot, path)
    doc = json.loads(path.read_text())
    text = edit(doc)
    path.write_text(text if isinstance(text, str) else json.dumps(doc))
    return path


@pytest.mark.parametrize(
    ("edit", "pattern"),
    [
        (lambda d: json.dumps(d).replace("0.1,", "NaN,", 1), "non-finite number NaN"),
        (lambda d: d["fourier"]["a"][2].__setitem__(1, "x"), "fourier.a"),
        (lambda d: d.__setitem__("format_version", 2), "format_version"),
        (lambda d: d.pop("periods"), "periods"),
        (lambda d: d.__setitem__("periods", 0), "periods"),
        (lambda d: d["fourier"].__setitem__("q0", [0.0] * 5), r"fourier.q0.*shape"),
        (lambda d: d["fourier"]["b"].pop(), r"fourier.b.*shape"),
        (lambda d: d["fourier"].__setitem__("base_frequency_hz", -1), "base_frequency_hz"),
        (lambda d: "{not json", "not a valid trajectory JSON"),
        (lambda d: d["limits"]["joints"][0].__setitem__("velocity", -1.0), "limits"),
    ],
)
def test_bad_files_give_one_line_naming_file_and_key(robot, tmp_path, edit, pattern) -> None:
    path = _corrupt(robot, tmp_path, edit)
    with pytest.raises(DataError, match=pattern) as err:
        load_trajectory(path)
    assert str(path) in str(err.value)
    assert "\n" not in str(err.value)


def test_nan_anywhere_in_the_numbers_is_refused(robot, tmp_path: Path) -> None:
    path = tmp_path / "t.json"
    make_file(robot, path)
    text = path.read_text()
    first_b = text.index('"b"')
    bad = text[:first_b] + text[first_b:].replace("[", "[Infinity, ", 2).replace(
        "[Infinity, ", "[", 1
    )
    path.write_text(bad)
    with pytest.raises(DataError, match="Infinity"):
        load_trajectory(path)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="cannot read"):
        load_trajectory(tmp_path / "nope.json")


def test_check_robot(robot, tmp_path: Path) -> None:
    path = tmp_path / "t.json"
    make_file(robot, path)
    doc = json.loads(path.read_text())
    doc["joint_names"] = ["a", "b", "c", "d", "e", "f"]
    path.write_text(json.dumps(doc))
    with pytest.raises(DataError, match="joint_names"):
        load_trajectory(path).check_robot(robot)
