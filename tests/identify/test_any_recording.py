"""``identify`` on recordings as other programs make them (issue 16, items 1, 3 and 4).

Logs are made here from the simulated TX-40: irregular time stamps, swapped or identical runs,
a payload attached to the loaded log only, and a controller-style current reference that does
not contain the payload's effect (the measured current does).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from drivegain.cli import main
from drivegain.config import resource_path
from drivegain.formats.log import RunMetadata
from drivegain.formats.logwriter import write_run
from drivegain.identify.synth import simulate_run

ROBOT = resource_path("tx40.toml")
PAYLOAD = resource_path("payloads/calibrated-4590g.toml")
TRAJ = {"fourier": {"base_frequency_hz": 0.2, "a": [[0.0] * 5] * 6, "b": [[0.0] * 5] * 6}}


def _log(
    world,
    path: Path,
    which: int,
    payload,
    seed: int,
    *,
    t: np.ndarray,
    period: float,
    reference_payload: bool = True,
    attach_payload: bool = False,
    run: str | None = None,
) -> Path:
    """A log sampled at the stamps ``t`` (s), declaring ``sync_period_s = period``.

    ``reference_payload=False``: the current reference is a controller's feed-forward computed
    without the payload, the measured current holds the payload's effect.
    """
    q, qd, qdd = world.excitations[which].evaluate(t)[:3]
    rng = np.random.default_rng(seed)
    common = dict(torque_noise=0.05, quantum=float(np.deg2rad(1e-3)))
    sim = simulate_run(world.model, world.truth, q, qd, qdd, payload=payload, rng=rng, **common)
    reference, measured = sim.current_reference, sim.current_reference
    if not reference_payload:
        ff = simulate_run(world.model, world.truth, q, qd, qdd, payload=None, rng=rng, **common)
        reference = ff.current_reference
    meta = RunMetadata(
        robot=world.robot.name,
        run=run or ("loaded" if payload is not None else "unloaded"),
        payload=payload.name if payload is not None else "none",
        joint_names=world.robot.joint_names,
        sync_period_s=period,
        started_at="2024-01-01T00:00:00.000Z",
    )
    att = [("trajectory.json", "application/json", json.dumps(TRAJ).encode())]
    if attach_payload:
        att.append((PAYLOAD.name, "application/toml", PAYLOAD.read_bytes()))
    return write_run(path, meta, t, sim.q, reference, measured, attachments=att)


def _stamps(seconds: float, seed: int) -> np.ndarray:
    """Steps of 10 or 12 ms at random, as the user's recording had."""
    steps = np.random.default_rng(seed).choice([0.010, 0.012], int(seconds / 0.011))
    return np.concatenate([[0.0], np.cumsum(steps)])


def _identify(*args: str | Path) -> int:
    return main(["identify", "--robot", str(ROBOT), *[str(a) for a in args]])


def _gains(out: Path) -> np.ndarray:
    doc = json.loads((out / "report.json").read_text())
    return np.array([g["value"] for g in doc["gains"]])


# --------------------------------------------------------------------------------------------
# Item 1: time stamps


@pytest.fixture(scope="module")
def irregular(world, tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("irregular")
    out = {}
    for label, which, pay, seed in (("a", 0, None, 1), ("b", 1, world.payload, 2)):
        t = _stamps(30.0, seed + 10)
        mean = float(t[-1] / (t.size - 1))
        out[label] = _log(world, d / f"{label}.mcap", which, pay, seed, t=t, period=mean)
        out[f"{label}-declared-10ms"] = _log(
            world, d / f"{label}10.mcap", which, pay, seed, t=t, period=0.010
        )
    return out


def test_irregular_time_stamps_are_resampled_and_reported(world, irregular, tmp_path) -> None:
    out = tmp_path / "r"
    code = _identify(
        "--unloaded", irregular["a"], "--loaded", irregular["b"], "--payload", PAYLOAD, "--out", out
    )
    assert code == 0
    # Independent truth: the simulation's gains (ignoring the stamps moved them by up to 6 %).
    assert np.all(np.abs(_gains(out) / world.truth.gains - 1) < 0.01)
    doc = json.loads((out / "report.json").read_text())
    tb = doc["runs"][0]["time_base"]
    steps = np.diff(_stamps(30.0, 11))  # run a's stamps
    assert tb["uniform"] is False
    assert tb["spread"] == pytest.approx(np.std(steps) / steps.mean(), rel=1e-6)
    assert tb["min_step_s"] == pytest.approx(0.010) and tb["max_step_s"] == pytest.approx(0.012)
    assert any("irregular time stamps" in n for n in doc["runs"][0]["notes"])
    assert "irregular time stamps" in (out / "report.md").read_text()
    # Good data: no diagnosis of the current channel (item 3).
    assert not [w for w in doc["warnings"] if "--current" in w]


def test_declared_period_disagreeing_with_stamps_is_refused(irregular, tmp_path, capsys) -> None:
    out = tmp_path / "r"
    code = _identify(
        "--unloaded",
        irregular["a-declared-10ms"],
        "--loaded",
        irregular["b"],
        "--payload",
        PAYLOAD,
        "--out",
        out,
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and not out.exists()
    assert str(irregular["a-declared-10ms"]) in err and "sync_period_s declares 10 ms" in err


def test_a_robot_file_without_acquisition_keys_identifies(world, irregular, tmp_path) -> None:
    """Item 6: no encoder counts, rated currents, limits of acceleration and jerk, node ids or
    a priori gains in the robot file: identification starts from the gear ratios."""
    drop = ("encoder_counts", "rated_current", "node_id", "acceleration_limit", "jerk_limit")
    lines = [
        ln
        for ln in ROBOT.read_text().splitlines()
        if ln.split("=")[0].strip() not in (*drop, "apriori_gain")
    ]
    bare = tmp_path / "bare.toml"
    bare.write_text("\n".join(lines) + "\n")
    out = tmp_path / "r"
    argv = ["identify", "--robot", str(bare), "--unloaded", str(irregular["a"])]
    argv += ["--loaded", str(irregular["b"]), "--payload", str(PAYLOAD), "--out", str(out)]
    assert main(argv) == 0
    assert np.all(np.abs(_gains(out) / world.truth.gains - 1) < 0.01)
    doc = json.loads((out / "report.json").read_text())
    assert [g["apriori"] for g in doc["gains"]] == [32, 32, 45, -48, 45, 32]
    assert doc["method"]["apriori_from_gear_ratio"] == world.robot.joint_names


# --------------------------------------------------------------------------------------------
# Item 4: swapped or identical runs, payload attached to the loaded log


@pytest.fixture(scope="module")
def short_logs(world, tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("short")
    t = np.arange(0.0, 3.0, 0.004)
    return {
        "a": _log(world, d / "a.mcap", 0, None, 1, t=t, period=0.004),
        "b": _log(world, d / "b.mcap", 1, world.payload, 2, t=t, period=0.004),
    }


def test_swapped_runs_are_refused_naming_them(short_logs, tmp_path, capsys) -> None:
    a, b = short_logs["a"], short_logs["b"]
    out = tmp_path / "r"
    code = _identify("--unloaded", b, "--loaded", a, "--payload", PAYLOAD, "--out", out)
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and not out.exists()
    assert "swapped runs" in err and str(a) in err and str(b) in err


def test_a_loaded_run_as_unloaded_is_refused(world, short_logs, tmp_path, capsys) -> None:
    t = np.arange(0.0, 3.0, 0.004)
    b2 = _log(world, tmp_path / "b2.mcap", 2, world.payload, 3, t=t, period=0.004)
    code = _identify(
        "--unloaded", short_logs["b"], "--loaded", b2, "--payload", PAYLOAD, "--out", tmp_path / "r"
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err
    assert f"--unloaded {short_logs['b']} is a loaded run" in err


def test_identical_runs_are_refused(short_logs, tmp_path, capsys) -> None:
    a = short_logs["a"]
    copy = tmp_path / "copy.mcap"
    shutil.copyfile(a, copy)
    for other in (a, copy):
        code = _identify("--unloaded", a, "--loaded", other, "--payload", PAYLOAD, "--out", "x")
        err = capsys.readouterr().err.strip()
        assert code == 2 and "are the same run" in err and str(other) in err


@pytest.fixture(scope="module")
def feedforward(world, tmp_path_factory) -> dict[str, Path]:
    """Runs whose current reference lacks the payload (the measured current has it), with the
    payload TOML attached to the loaded log."""
    d = tmp_path_factory.mktemp("ff")
    t = np.arange(0.0, 30.0, 1 / 100)
    return {
        "a": _log(world, d / "a.mcap", 0, None, 1, t=t, period=0.01),
        "b": _log(
            world,
            d / "b.mcap",
            1,
            world.payload,
            2,
            t=t,
            period=0.01,
            reference_payload=False,
            attach_payload=True,
        ),
    }


def test_payload_is_taken_from_the_loaded_log_and_measured_current_works(
    world, feedforward, tmp_path
) -> None:
    out = tmp_path / "r"
    code = _identify(
        "--unloaded", feedforward["a"], "--loaded", feedforward["b"], "--current", "measured",
        "--out", out,
    )  # fmt: skip
    assert code == 0
    assert np.all(np.abs(_gains(out) / world.truth.gains - 1) < 0.01)
    doc = json.loads((out / "report.json").read_text())
    assert doc["payload"]["name"] == world.payload.name
    assert doc["runs"][1]["current"] == "measured"


# --------------------------------------------------------------------------------------------
# Item 3: which current


def test_current_without_the_payload_is_refused_by_ml(feedforward, tmp_path, capsys) -> None:
    """The default estimator finds no maximum (the scale is not in the data) and says why."""
    out = tmp_path / "r"
    code = _identify("--unloaded", feedforward["a"], "--loaded", feedforward["b"], "--out", out)
    err = capsys.readouterr().err
    assert code != 0 and not out.exists()
    assert "grow without bound" in err and "--current measured" in err
    assert len(err.strip().splitlines()) == 1


def test_current_without_the_payload_is_diagnosed(feedforward, tmp_path, capsys) -> None:
    """The paper's estimator gives a solution: the report's warnings say what is wrong."""
    out = tmp_path / "r"
    code = _identify(
        "--unloaded", feedforward["a"], "--loaded", feedforward["b"], "--estimator", "paper",
        "--out", out,
    )  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0
    warnings = json.loads((out / "report.json").read_text())["warnings"]
    unchanged = [w for w in warnings if "do not change with the payload" in w]
    meaningless = [w for w in warnings if "gains are meaningless" in w]
    assert unchanged and "--current measured" in unchanged[0] and "nominal 4.59 kg" in unchanged[0]
    assert meaningless
    assert "--current measured" in err


# --------------------------------------------------------------------------------------------
# Item 2: the converter, end to end


def test_converted_irregular_table_identifies(world, table_csv, tmp_path: Path) -> None:
    """End to end: a table with 10/12 ms steps → logs → identify, gains within 1 %."""
    paths = {}
    for label, which, pay, seed in (("unloaded", 0, None, 1), ("loaded", 1, world.payload, 2)):
        rng = np.random.default_rng(seed)
        t = np.concatenate([[0.0], np.cumsum(rng.choice([0.010, 0.012], 2700))])
        q, qd, qdd = world.excitations[which].evaluate(t)[:3]
        sim = simulate_run(world.model, world.truth, q, qd, qdd, payload=pay, rng=rng,
                           torque_noise=0.05, quantum=float(np.deg2rad(1e-3)))  # fmt: skip
        data = {"time": t + 17.0}
        data |= {f"q{j + 1}": sim.q[:, j] for j in range(6)}
        data |= {f"v{j + 1}": sim.current_reference[:, j] for j in range(6)}
        table = table_csv(tmp_path / f"{label}.csv", data)
        argv = ["convert", "table", "--input", str(table), "--time", "time", "--position", "q{}"]
        argv += ["--current-reference", "v{}", "--robot", str(ROBOT), "--run", label]
        if pay is not None:
            argv += ["--payload", str(PAYLOAD)]
        paths[label] = tmp_path / f"{label}.mcap"
        assert main([*argv, "--out", str(paths[label])]) == 0
    out = tmp_path / "r"
    argv = ["identify", "--robot", str(ROBOT), "--unloaded", str(paths["unloaded"])]
    argv += ["--loaded", str(paths["loaded"]), "--out", str(out)]  # payload: the attached one
    assert main(argv) == 0
    doc = json.loads((out / "report.json").read_text())
    gains = np.array([g["value"] for g in doc["gains"]])
    assert np.all(np.abs(gains / world.truth.gains - 1) < 0.01)
    assert doc["runs"][0]["time_base"]["uniform"] is False
