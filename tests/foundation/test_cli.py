"""The command line: help, version, model info, and exit statuses."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from drivegain import __version__
from drivegain.cli import main
from drivegain.config import resource_path


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "drivegain", *args], capture_output=True, text=True, check=False
    )


def test_version_and_help() -> None:
    res = run("--version")
    assert res.returncode == 0 and res.stdout.strip() == f"drivegain {__version__}"
    res = run("--help")
    assert res.returncode == 0
    for cmd in ("demo", "excite", "acquire", "daemon", "identify", "convert", "model"):
        assert cmd in res.stdout
    for sub in (["identify"], ["convert", "csv"], ["model", "info"], ["excite"], ["demo"]):
        assert run(*sub, "--help").returncode == 0


def test_model_info_prints_counts(capsys) -> None:
    assert main(["model", "info", "--robot", str(resource_path("tx40.toml"))]) == 0
    out = capsys.readouterr().out
    assert "standard parameters: 86" in out
    assert "base parameters: 60" in out
    assert "ZZ1R = ZZ1 + Ia1 + YY2" in out
    assert "cond(W_base)" in out


def test_bad_robot_file_exit_2_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "robot.toml"
    bad.write_text("[robot]\nname = 1\n")
    res = run("model", "info", "--robot", str(bad))
    assert res.returncode == 2
    assert res.stderr.strip().count("\n") == 0
    assert "Traceback" not in res.stderr
    assert str(bad) in res.stderr


def test_debug_before_or_after_the_command_shows_the_traceback(tmp_path: Path) -> None:
    bad = tmp_path / "robot.toml"
    bad.write_text("[robot]\nname = 1\n")
    for argv in (["--debug", "model", "info"], ["model", "info", "--debug"]):
        res = run(*argv, "--robot", str(bad))
        assert res.returncode == 2
        assert "Traceback" in res.stderr, argv


@pytest.mark.parametrize(
    "argv",
    [
        ["model", "info", "--samples", "0"],
        ["model", "info", "--samples", "-5"],
        ["model", "info", "--samples", "many"],
        ["excite", "--out", "t.json", "--base-frequency", "1e308"],
        ["excite", "--out", "t.json", "--harmonics", "10000"],
        ["excite", "--out", "t.json", "--budget", "nan"],
        [
            "convert",
            "csv",
            "--positions",
            "p.csv",
            "--currents",
            "c.csv",
            "--out",
            "r.mcap",
            "--rate",
            "1e-300",
        ],
    ],
    ids=lambda a: " ".join(a[:1] + a[-2:]),
)
def test_numbers_out_of_bounds_one_line_exit_2(tmp_path: Path, argv: list[str]) -> None:
    robot = str(resource_path("tx40.toml"))
    res = subprocess.run(
        [sys.executable, "-m", "drivegain", *argv, "--robot", robot],
        capture_output=True,
        text=True,
        check=False,
        cwd=tmp_path,
        timeout=60,
    )
    assert res.returncode == 2, res.stderr
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr
    assert argv[-2] in res.stderr
    assert list(tmp_path.iterdir()) == []


def test_outputs_are_refused_before_any_work(tmp_path: Path) -> None:
    log = tmp_path / "recorded.mcap"
    log.write_bytes(b"a recorded log")
    csv = tmp_path / "x.csv"
    csv.write_text("1,2,3,4,5,6\n")
    robot = str(resource_path("tx40.toml"))
    conv = ["convert", "csv", "--positions", str(csv), "--currents", str(csv), "--rate", "100"]
    cases = [
        ([*conv, "--robot", robot, "--out", str(log)], "refusing to overwrite"),
        ([*conv, "--robot", robot, "--out", str(tmp_path / "x.txt")], "must end with .mcap"),
        ([*conv, "--robot", robot, "--out", str(tmp_path)], "is a folder"),
        (["demo", "--out", str(log)], "exists and is not a folder"),
        (["excite", "--robot", robot, "--out", str(tmp_path)], "is a folder"),
        (
            ["identify", "--robot", robot, "--unloaded", str(log), "--out", str(log / "r")],
            "is not a folder",
        ),
    ]
    for argv, fragment in cases:
        res = run(*argv)
        assert res.returncode == 2, (argv, res.stderr)
        assert fragment in res.stderr and res.stderr.count("\n") == 1, res.stderr
    assert log.read_bytes() == b"a recorded log"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["recorded.mcap", "x.csv"]


def test_help_shows_every_default_and_robot_names_work(capsys) -> None:
    from drivegain.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, p in sub.choices.items():
        for action in p._actions:
            if action.default not in (None, False, argparse.SUPPRESS) and action.help:
                assert "(default:" in p.format_help(), (name, action.dest)
                assert f"(default: {action.default})" in " ".join(p.format_help().split()), (
                    name,
                    action.dest,
                )
    assert main(["model", "info", "--robot", "tx40", "--samples", "20"]) == 0
    assert "Staubli TX-40" in capsys.readouterr().out
