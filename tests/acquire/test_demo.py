"""``drivegain demo`` end to end over the mocked bus (the one slow test of this area)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rich.console import Console

from drivegain.acquire.demo import run_demo
from drivegain.config import load_truth, resource_path


@pytest.mark.slow
def test_demo_identifies_the_true_gains(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    console = Console(file=(tmp_path / "demo.txt").open("w"), width=120)
    result = run_demo(out, seed=1, console=console, progress=False)
    console.file.close()

    truth = np.asarray(load_truth(resource_path("sim/tx40-truth.toml")).gains)
    np.testing.assert_array_equal(result.true, truth)
    # the a priori gains are 5-24 % off; the identified ones within 1 % of the simulator's truth
    assert np.max(np.abs(result.apriori - truth) / np.abs(truth)) > 0.1
    rel = np.abs(result.identified - truth) / np.abs(truth)
    assert np.all(rel < 0.01), rel

    for log in (result.unloaded, result.loaded):
        with open(log, "rb") as fh:
            reader = make_reader(fh)
            cycles = [
                json.loads(m.data)["cycle"]
                for _s, _c, m in reader.iter_messages(topics=["/joint_states"])
            ]
        assert cycles == list(range(len(cycles))) and len(cycles) > 5000
    report = json.loads((result.report_dir / "report.json").read_text())
    assert [g["value"] for g in report["gains"]] == pytest.approx(result.identified.tolist())
    text = (tmp_path / "demo.txt").read_text()
    assert "a priori" in text and "true" in text and str(result.report_dir) in text

    # the report says what the terminal says: true gains and errors, in all three files
    md = (result.report_dir / "report.md").read_text()
    section = md[md.index("## Simulation truth") :]
    assert md.index("## Drive gains") < md.index("## Simulation truth") < md.index("## Plots")
    for j in range(truth.size):
        err = 100 * (result.identified[j] - truth[j]) / truth[j]  # computed here, not by demo
        assert f"| {truth[j]:.4g} |" in section and f"{err:+.3f} |" in section
    assert "Simulation truth" in (result.report_dir / "report.html").read_text()
    assert report["simulation_truth"]["gains"] == truth.tolist()
