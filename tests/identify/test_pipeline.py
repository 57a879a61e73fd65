"""``drivegain identify`` end to end on simulated MCAP logs: reports, options, bad input."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from drivegain.cli import main
from drivegain.config import resource_path
from drivegain.identify.cases import CaseCovariance
from drivegain.identify.leaveout import MISFIT_KAPPA

ROBOT = resource_path("tx40.toml")
PAYLOAD = resource_path("payloads/calibrated-4590g.toml")
VALIDATION = resource_path("payloads/validation-1686g.toml")


@pytest.fixture(scope="module")
def logs(run_logs, tmp_path_factory) -> dict[str, Path]:
    return run_logs(tmp_path_factory.mktemp("logs"), {"a": 1, "b": 2, "c": 3}, seconds=30.0)


def _identify_both(logs: dict[str, Path], *args: str | Path) -> int:
    """``drivegain identify`` of the unloaded run a and the loaded run b, then ``args``."""
    argv = ["--unloaded", logs["a"], "--loaded", logs["b"], "--payload", PAYLOAD, *args]
    return main(["identify", "--robot", str(ROBOT), *[str(a) for a in argv]])


@pytest.fixture(scope="module")
def full_report(logs, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs") / "report"
    validate = ("--validate", logs["c"], "--validate-payload", VALIDATION)
    code = _identify_both(logs, *validate, "--out", out)
    assert code == 0
    return out


def _number(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def test_report_json_follows_contracts_5(full_report: Path, world) -> None:
    doc = json.loads((full_report / "report.json").read_text())
    assert doc["format_version"] == 1
    assert [g["joint"] for g in doc["gains"]] == world.robot.joint_names
    for g in doc["gains"]:
        assert all(_number(g[k]) for k in ("value", "std", "rel_std_percent"))
        assert g["rel_std_percent"] == pytest.approx(100 * g["std"] / abs(g["value"]))
    gains = np.array([g["value"] for g in doc["gains"]])
    assert np.all(np.abs(gains / world.truth.gains - 1) < 0.01)
    assert set(doc["payload"]) >= {"mass", "MX", "MY", "MZ", "XX", "XY", "XZ", "YY", "YZ", "ZZ"}
    assert all(
        _number(doc["payload"][k]["value"]) and _number(doc["payload"][k]["std"])
        for k in ("mass", "MX", "ZZ")
    )
    assert doc["payload"]["mass"]["value"] == pytest.approx(4.59, rel=0.01)
    for b in doc["base_parameters"]:
        assert isinstance(b["name"], str) and _number(b["value"]) and _number(b["std"])
        assert b["rel_std_percent"] is None or _number(b["rel_std_percent"])
    assert _number(doc["residual"]["norm"]) and 0 < doc["residual"]["relative"] < 0.01
    m = doc["method"]
    assert m["estimator"] == "ML" and m["alpha"] is None  # the default estimator
    assert isinstance(m["samples"], int) and m["samples"] > 1000
    # Extras: both cases, the validation payload, the α curve, cross-validation.
    assert set(doc["cases"]) == {"case1", "case2"}
    # Case 2's σ under the ML gains' error model, or Newey-West's on the entries it keeps when
    # that model finds a drive's reversals misfit; Case 1's (a priori gains) Newey-West
    case2 = doc["cases"]["case2"]
    misfit = [k["drive"] for k in doc["ml"]["reversal_variance"] if k["kappa"] >= MISFIT_KAPPA]
    if misfit:  # these logs: j4 (κ̂ 5.8: a slow reversal under the encoder's quantum)
        assert case2["covariance"] == CaseCovariance.NEWEY_WEST_KEPT
        assert case2["left_out_entries"] > 0
        text = (full_report / "report.md").read_text()
        assert f"case2 left {case2['left_out_entries']} entries" in text
    else:
        assert case2["covariance"] == CaseCovariance.ERROR_MODEL
        assert case2["left_out_entries"] == 0
    assert doc["cases"]["case1"]["left_out_entries"] == 0
    assert doc["cases"]["case1"]["covariance"] == "HAC (Newey-West, Bartlett kernel)"
    assert doc["validation"]["case2"]["mass"]["value"] == pytest.approx(1.686, rel=0.02)
    ml = doc["ml"]
    assert len(ml["noise_std"]) == 6 and all(_number(s["std"]) for s in ml["noise_std"])
    assert isinstance(ml["covariance_lag_samples"], int) and ml["converged"] is True
    assert 0.0 <= ml["eiv_test"]["p_value"] <= 1.0 and ml["eiv_test"]["dof"] == 6
    velocities = {"j1", "j2", "j3", "j4", "j5", "j6", "motor j5+j6"}
    for c in ml["reversal_coulomb"]:
        assert c["velocity"] in velocities and c["unit"] == "N·m"
        assert _number(c["value"]) and _number(c["std"]) and c["std"] > 0
    # null unless a run spans 1.5 periods of a known excitation (these short logs do not)
    factors = ml["gain_std_repeat_factor"]
    assert factors is None or (len(factors) == 6 and all(_number(f) and f >= 1.0 for f in factors))
    assert "wtls" not in doc
    assert len(doc["cross_validation"]["joints"]) == 6


def test_bootstrap_sigma_is_reported_beside_the_hac_sigma(full_report, logs, tmp_path) -> None:
    """``--bootstrap N``: the same gains and σ, plus ``ml.bootstrap`` and a Markdown line."""
    out = tmp_path / "boot"
    assert _identify_both(logs, "--bootstrap", "12", "--no-plots", "--out", out) == 0
    doc = json.loads((out / "report.json").read_text())
    plain = json.loads((full_report / "report.json").read_text())
    assert [g["value"] for g in doc["gains"]] == [g["value"] for g in plain["gains"]]
    assert "bootstrap" not in plain["ml"]
    boot = doc["ml"]["bootstrap"]
    assert boot["replicates"] == 12 and boot["failed"] == 0 and boot["block_samples"] >= 13
    hac = np.array([g["std"] for g in doc["gains"]])
    spread = np.array([s["std"] for s in boot["gain_std"]])
    # Twelve replicates estimate a σ to about ±40 %: the same size, not the same number.
    assert np.all((spread > 0.3 * hac) & (spread < 3.0 * hac)), spread / hac
    assert set(boot["payload_std"]) == set(doc["ml"]["payload_unknown"])
    assert "Bootstrap (12 replicates" in (out / "report.md").read_text()


def test_markdown_and_plots(full_report: Path) -> None:
    md = (full_report / "report.md").read_text()
    for title in ("Table 3", "Table 2", "Table 4", "Table 5", "friction forms"):
        assert title in md
    assert "Maximum-likelihood diagnostics" in md and "Errors-in-variables test" in md
    pngs = ("torques_unloaded.png", "torques_loaded.png")
    for png in pngs:
        data = (full_report / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
        assert f"]({png})" in md
    assert not list(full_report.parent.glob(".report.*"))  # no staging folder left


def test_gains_from_a_report_or_a_toml_skip_wtls(full_report, logs, tmp_path, capsys) -> None:
    out = tmp_path / "again"
    assert _identify_both(logs, "--gains", full_report / "report.json", "--out", out) == 0
    first = json.loads((full_report / "report.json").read_text())
    doc = json.loads((out / "report.json").read_text())
    assert doc["method"]["estimator"] == "IDIM-WLS"
    assert [g["value"] for g in doc["gains"]] == [g["value"] for g in first["gains"]]
    assert [g["std"] for g in doc["gains"]] == [g["std"] for g in first["gains"]]
    toml = tmp_path / "gains.toml"
    toml.write_text(
        "values = [33.7, 32.2, 24.1, -8.8, 16.5, 6.82]\nstd = [0.1, 0.1, 0.1, 0.1, 0.1, 0.1]\n"
    )
    out2 = tmp_path / "toml"
    assert (
        main(
            [
                "identify",
                "--robot",
                str(ROBOT),
                "--unloaded",
                str(logs["a"]),
                "--gains",
                str(toml),
                "--out",
                str(out2),
            ]
        )
        == 0
    )
    doc2 = json.loads((out2 / "report.json").read_text())
    assert [g["value"] for g in doc2["gains"]] == [33.7, 32.2, 24.1, -8.8, 16.5, 6.82]
    assert "payload" not in doc2
    assert "IDIM-WLS" in capsys.readouterr().out


def test_existing_out_folder_keeps_other_files(logs, tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "report.json").write_text("old")
    assert (
        main(["identify", "--robot", str(ROBOT), "--unloaded", str(logs["a"]), "--out", str(out)])
        == 0
    )
    assert (out / "notes.txt").read_text() == "mine"
    assert json.loads((out / "report.json").read_text())["format_version"] == 1


def _bad_inputs(sim_log, logs, tmp: Path) -> dict[str, list[str]]:
    base = ["identify", "--robot", str(ROBOT), "--unloaded", str(logs["a"])]
    both = [*base, "--loaded", str(logs["b"]), "--payload", str(PAYLOAD)]
    text = tmp / "notes.mcap"
    text.write_text("not a log\n")
    short = sim_log(tmp / "short.mcap", 0, None, 5, seconds=0.4)
    five = sim_log(tmp / "five.mcap", 0, None, 6, seconds=30.0, joints=5)
    bad_gains = tmp / "gains.toml"
    bad_gains.write_text("values = [1.0, 2.0]\n")
    a_file = tmp / "file"
    a_file.write_text("")
    return {
        "loaded without payload": [*base, "--loaded", str(logs["b"])],
        "not an MCAP file": ["identify", "--robot", str(ROBOT), "--unloaded", str(text)],
        "missing log": ["identify", "--robot", str(ROBOT), "--unloaded", str(tmp / "no.mcap")],
        "wrong joint count": ["identify", "--robot", str(ROBOT), "--unloaded", str(five)],
        "too few samples": ["identify", "--robot", str(ROBOT), "--unloaded", str(short)],
        "gains of wrong length": [*base, "--gains", str(bad_gains)],
        "unknown gains keyword": [*base, "--gains", "manufacturer"],
        "negative alpha": [*base, "--alpha", "-1"],
        "cut-off above Nyquist": [*base, "--cutoff", "500"],
        "out is a file": [
            "identify",
            "--robot",
            str(ROBOT),
            "--unloaded",
            str(logs["a"]),
            "--out",
            str(a_file),
        ],
        "bad payload file": [*base, "--loaded", str(logs["b"]), "--payload", str(bad_gains)],
        "too few bootstrap replicates": [*both, "--bootstrap", "3"],
        "bootstrap of the paper's estimator": [*both, "--estimator", "paper", "--bootstrap", "10"],
        "bootstrap without a loaded run": [*base, "--bootstrap", "10"],
    }


def test_bad_input_exits_2_with_one_line_and_writes_nothing(
    sim_log, logs, tmp_path, capsys
) -> None:
    cases = _bad_inputs(sim_log, logs, tmp_path)
    for name, argv in cases.items():
        out = tmp_path / f"out-{name.replace(' ', '-')}"
        if "--out" not in argv:
            argv = [*argv, "--out", str(out)]
        code = main(argv)
        err = capsys.readouterr().err.strip()
        assert code == 2, f"{name}: exit {code}, stderr {err!r}"
        assert err.startswith("drivegain: error:") and "\n" not in err, f"{name}: {err!r}"
        assert not out.exists(), name
    assert not list(tmp_path.glob(".out-*"))


def test_failure_midway_leaves_nothing(logs, tmp_path, monkeypatch, capsys) -> None:
    import drivegain.identify.plots as plots

    def broken(*_a, **_k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(plots, "write_plots", broken)
    out = tmp_path / "out"
    code = main(
        ["identify", "--robot", str(ROBOT), "--unloaded", str(logs["a"]), "--out", str(out)]
    )
    assert code == 1
    assert "disk full" in capsys.readouterr().err
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out")]


def test_sigterm_midway_leaves_nothing(logs, tmp_path, monkeypatch, capsys) -> None:
    import os
    import signal
    import time

    import drivegain.identify.plots as plots

    def terminated(*_a, **_k):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler raises in this thread before the sleep ends
        raise AssertionError("SIGTERM was not turned into an exception")

    monkeypatch.setattr(plots, "write_plots", terminated)
    out = tmp_path / "out"
    code = main(
        ["identify", "--robot", str(ROBOT), "--unloaded", str(logs["a"]), "--out", str(out)]
    )
    assert code == 128 + signal.SIGTERM
    assert "terminated" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []  # no output folder, no hidden staging folder
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the handler is restored


def test_rerun_removes_what_the_earlier_run_wrote_and_this_one_did_not(logs, tmp_path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "old-plot.png").write_bytes(b"png of an earlier run")
    (out / "report.json").write_text(json.dumps({"files": ["old-plot.png", "report.json"]}))
    argv = ["identify", "--robot", str(ROBOT), "--unloaded", str(logs["a"]), "--out", str(out)]
    assert main(argv) == 0
    doc = json.loads((out / "report.json").read_text())
    assert not (out / "old-plot.png").exists()
    assert (out / "notes.txt").read_text() == "mine"
    assert sorted(doc["files"]) == sorted(p.name for p in out.iterdir() if p.name != "notes.txt")
