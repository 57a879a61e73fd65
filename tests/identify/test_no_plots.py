"""``identify --no-plots`` (issue 19): the same report without figures, and it says so."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from drivegain.cli import main
from drivegain.config import resource_path


def test_no_plots_writes_no_figure_and_says_so(
    real_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "report"
    argv = ["identify", "--robot", str(resource_path("tx40.toml")), "--unloaded", str(real_log)]
    code = main([*argv, "--gains", "gear-ratios", "--no-plots", "--out", str(out)])
    assert code == 0
    assert not list(out.glob("*.png"))
    doc = json.loads((out / "report.json").read_text())
    assert "not rendered" in doc["figures"] and "--no-plots" in doc["figures"]
    assert not any(name.endswith(".png") for name in doc["files"])
    assert "not rendered" in (out / "report.md").read_text()
    assert "figures not rendered" in capsys.readouterr().out
    assert len(doc["gains"]) == 6
