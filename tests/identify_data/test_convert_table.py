"""``drivegain convert table``: one table with a time column → a log with real time stamps
(issue 16, item 2)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from drivegain.cli import main
from drivegain.config import resource_path
from drivegain.errors import InputError
from drivegain.formats.logreader import read_run
from drivegain.identify.table import convert_table

ROBOT = resource_path("tx40.toml")
N = np.array([32.0, 32.0, 45.0, -48.0, 45.0, 32.0])


def _data(rows: int = 200, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = 1000.0 + np.concatenate([[0.0], np.cumsum(rng.choice([0.010, 0.012], rows - 1))])
    return {
        "time": t,
        **{f"q{j}": rng.standard_normal(rows) for j in range(1, 7)},
        **{f"qd{j}": rng.standard_normal(rows) for j in range(1, 7)},
        **{f"iref{j}": rng.standard_normal(rows) for j in range(1, 7)},
        **{f"i{j}": rng.standard_normal(rows) for j in range(1, 7)},
        **{f"tau{j}": rng.standard_normal(rows) for j in range(1, 7)},
        **{f"qs{j}": rng.standard_normal(rows) for j in range(1, 7)},
    }


def _cols(data: dict[str, np.ndarray], prefix: str) -> np.ndarray:
    return np.column_stack([data[f"{prefix}{j}"] for j in range(1, 7)])


def test_csv_with_real_time_stamps_and_columns_by_name(
    tmp_path: Path, table_csv: Callable[..., Path]
) -> None:
    data = _data()
    table = table_csv(tmp_path / "run.csv", data)
    out = convert_table(
        table, ROBOT, time="time", position="q{}", current_reference="iref{}",
        current="i1,i2,i3,i4,i5,i6", setpoint="qs{}", out=tmp_path / "a.mcap",
    )  # fmt: skip
    log = read_run(out)
    # Independent: the table's own columns.
    np.testing.assert_allclose(log.t, data["time"] - data["time"][0], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(log.position, _cols(data, "q"))
    np.testing.assert_array_equal(log.current_reference, _cols(data, "iref"))
    np.testing.assert_array_equal(log.current, _cols(data, "i"))
    np.testing.assert_array_equal(log.setpoint, _cols(data, "qs"))
    span = data["time"][-1] - data["time"][0]
    assert log.sync_period_s == pytest.approx(span / 199, rel=1e-12)
    assert log.meta["run"] == "unloaded" and log.meta["payload"] == "none"


def test_columns_by_number_rows_and_time_window(
    tmp_path: Path, table_csv: Callable[..., Path]
) -> None:
    data = _data()
    names = list(data)
    table = table_csv(tmp_path / "run.csv", data)
    numbers = ",".join(str(names.index(f"iref{j}") + 1) for j in range(1, 7))
    out = convert_table(
        table, ROBOT, time="1", position="q{}", current_reference=numbers,
        rows="11:150", out=tmp_path / "a.mcap",
    )  # fmt: skip
    log = read_run(out)
    np.testing.assert_array_equal(log.current_reference, _cols(data, "iref")[10:150])
    np.testing.assert_allclose(log.t, data["time"][10:150] - data["time"][10], atol=1e-9)
    rel = data["time"] - data["time"][0]
    out2 = convert_table(
        table, ROBOT, time="time", position="q{}", current_reference="iref{}",
        start=0.5, end=1.5, out=tmp_path / "b.mcap",
    )  # fmt: skip
    log2 = read_run(out2)
    inside = (rel >= 0.5) & (rel <= 1.5)
    assert log2.position.shape[0] == int(inside.sum())
    np.testing.assert_array_equal(log2.position, _cols(data, "q")[inside])


def test_motor_side_positions_are_converted(tmp_path: Path, table_csv: Callable[..., Path]) -> None:
    data = _data()
    table = table_csv(tmp_path / "run.csv", data)
    out = convert_table(
        table, ROBOT, time="time", position="q{}", current_reference="iref{}",
        motor_side=True, out=tmp_path / "a.mcap",
    )  # fmt: skip
    qm = _cols(data, "q")
    q = qm / N  # written out: motor 6 turns with N6·(q5 + q6)
    q[:, 5] = qm[:, 5] / N[5] - q[:, 4]
    np.testing.assert_allclose(read_run(out).position, q, rtol=1e-12, atol=1e-15)


def test_parquet(tmp_path: Path) -> None:
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    data = _data()
    path = tmp_path / "run.parquet"
    pq.write_table(pa.table({k: pa.array(v) for k, v in data.items()}), path)
    out = convert_table(
        path, ROBOT, time="time", position="q{}", current_reference="iref{}",
        current="i{}", out=tmp_path / "a.mcap",
    )  # fmt: skip
    log = read_run(out)
    np.testing.assert_array_equal(log.current, _cols(data, "i"))
    np.testing.assert_allclose(log.t, data["time"] - data["time"][0], atol=1e-9)


def test_refuses_to_overwrite_a_log(tmp_path: Path, table_csv: Callable[..., Path], capsys) -> None:
    table = table_csv(tmp_path / "run.csv", _data())
    out = tmp_path / "a.mcap"
    out.write_bytes(b"precious")
    with pytest.raises(InputError, match="refusing to overwrite"):
        convert_table(
            table, ROBOT, time="time", position="q{}", current_reference="iref{}", out=out
        )
    argv = ["convert", "table", "--input", str(table), "--time", "time", "--position", "q{}"]
    argv += ["--current-reference", "iref{}", "--robot", str(ROBOT), "--out", str(out)]
    assert main(argv) == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    assert out.read_bytes() == b"precious"


def test_unknown_column_is_one_line_naming_it(
    tmp_path: Path, table_csv: Callable[..., Path], capsys
) -> None:
    table = table_csv(tmp_path / "run.csv", _data())
    argv = ["convert", "table", "--input", str(table), "--time", "time", "--position", "pos{}"]
    argv += [
        "--current-reference",
        "iref{}",
        "--robot",
        str(ROBOT),
        "--out",
        str(tmp_path / "x.mcap"),
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "no column 'pos1'" in err and "--position" in err
    assert not (tmp_path / "x.mcap").exists()


def test_help_shows_the_layout_with_an_example(capsys) -> None:
    assert main(["convert", "table", "--help"]) == 0
    text = capsys.readouterr().out
    assert "Expected layout" in text and "time,q1" in text
    assert "drivegain convert table --input run.csv" in text
