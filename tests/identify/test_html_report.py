"""``report.html``: self-contained, same content as ``report.md``, figures render in a browser.

The browser check opens the file in headless Chromium (Debian package ``chromium``); it is
skipped, with the reason, where that is not installed.
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from drivegain.cli import main
from drivegain.config import resource_path
from drivegain.identify.html import html_report

CHROMIUM = os.environ.get("DRIVEGAIN_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"


@pytest.fixture(scope="module")
def report(run_logs, tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("html")
    # no encoder quantum, no trajectory attached
    logs = run_logs(d, {"a": 1, "b": 2}, seconds=12.0, quantum=0.0, trajectory=False)
    a, b = logs["a"], logs["b"]
    out = d / "report"
    argv = ["identify", "--robot", str(resource_path("tx40.toml")), "--unloaded", str(a)]
    argv += ["--loaded", str(b), "--payload", str(resource_path("payloads/calibrated-4590g.toml"))]
    # The paper's estimator: the α count below is its (the default ML has no α).
    assert main([*argv, "--estimator", "paper", "--out", str(out)]) == 0
    return out


def test_html_is_self_contained_and_says_what_the_markdown_says(report: Path) -> None:
    text = (report / "report.html").read_text(encoding="utf-8")
    md = (report / "report.md").read_text(encoding="utf-8")
    images = re.findall(r'<img src="([^"]*)"', text)
    linked = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert len(images) == len(linked) >= 4  # torques per run, α, singular values
    for src, name in zip(images, linked, strict=True):
        head, _, data = src.partition(",")
        assert head == "data:image/png;base64"
        assert base64.b64decode(data) == (report / name).read_bytes()
    assert not re.search(r"""(src|href)=["'](?!data:|#)""", text)  # nothing fetched
    # every Markdown heading is an HTML heading, in the same order
    heads = [h.strip() for h in re.findall(r"^#+ (.*)$", md, flags=re.M)]
    html_heads = [h.replace("&quot;", '"') for h in re.findall(r"<h\d>(.*?)</h\d>", text)]
    assert html_heads == heads
    assert "report.html" in json.loads((report / "report.json").read_text())["files"]


def test_html_escapes_the_markdown_text(tmp_path: Path) -> None:
    out = html_report("# r\n\nrun `<script>` from <b>x</b>\n\n![gone](../secret.png)\n", tmp_path)
    assert "<script>" not in out and "<b>" not in out
    assert 'src="../secret.png"' in out  # not a file of the folder: left as it is, not read


@pytest.mark.skipif(
    not Path(CHROMIUM).exists(),
    reason=f"headless Chromium not found ({CHROMIUM}): install the Debian package 'chromium'",
)
def test_figures_render_in_headless_chromium(report: Path, tmp_path: Path) -> None:
    # A copy with a probe script: after load it writes every image's natural size into the
    # DOM that --dump-dom prints (the report itself carries no script).
    probe = (
        "<script>window.addEventListener('load', () => document.body.setAttribute("
        "'data-images', JSON.stringify([...document.images].map("
        "i => [i.complete, i.naturalWidth, i.naturalHeight]))));</script>"
    )
    page = tmp_path / "probe.html"
    page.write_text(
        (report / "report.html").read_text(encoding="utf-8").replace("</body>", probe + "</body>"),
        encoding="utf-8",
    )
    cmd = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",  # tests may run as root in a container
        "--disable-gpu",
        "--no-first-run",
        f"--user-data-dir={tmp_path / 'profile'}",
        "--virtual-time-budget=10000",
        "--dump-dom",
        page.as_uri(),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    found = re.search(r'data-images="([^"]*)"', proc.stdout)
    assert found, f"no probe result (exit {proc.returncode}): {proc.stderr[-500:]}"
    images = json.loads(found.group(1).replace("&quot;", '"'))
    from PIL import Image

    expected = []
    for name in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", (report / "report.md").read_text()):
        with Image.open(report / name) as im:
            expected.append([True, *im.size])
    assert images == expected  # every figure decoded, at its own pixel size


def test_alpha_count_matches_the_progress_display(report: Path) -> None:
    from drivegain.identify.gains import DEFAULT_ALPHA_GRID

    doc = json.loads((report / "report.json").read_text())
    tried = [a for a, _ in doc["wtls"]["alpha_curve"]]
    md = (report / "report.md").read_text()
    # the progress display counts "α grid k/15"; the report splits its total the same way
    grid = len(DEFAULT_ALPHA_GRID)
    assert f"over {len(tried)} values (the {grid} of the log-spaced grid, then " in md
    assert f"then {len(tried) - grid} refined around the best" in md
