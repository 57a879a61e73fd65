"""The command line: help, version, model info, and exit statuses."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

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
