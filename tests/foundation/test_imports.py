"""Start-up stays light (issue 19): the command line imports no heavy library until a
subcommand that needs it runs. Checked in a fresh interpreter through ``sys.modules``, so the
test is about behaviour, not time."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

#: libraries that cost from a tenth of a second to seconds to import
HEAVY = (
    "scipy",
    "scipy.signal",
    "scipy.stats",
    "scipy.optimize",
    "matplotlib",
    "pinocchio",
    "cvxpy",
    "dask",
    "distributed",
    "pyarrow",
    "canopen",
    "can",
    "mcap",
)


def _loaded_after(code: str) -> list[str]:
    probe = f"{code}\nimport json, sys\nprint(json.dumps(sorted(sys.modules)))"
    out = subprocess.run(
        [sys.executable, "-c", probe], check=True, capture_output=True, text=True, timeout=120
    )
    loaded = set(json.loads(out.stdout.strip().splitlines()[-1]))
    return [m for m in HEAVY if m in loaded]


def test_importing_the_command_line_loads_no_heavy_library() -> None:
    assert _loaded_after("import drivegain.cli") == []


@pytest.mark.parametrize("argv", [["--help"], ["identify", "--help"], ["excite", "--help"]])
def test_help_loads_no_heavy_library(argv: list[str]) -> None:
    code = (
        "import contextlib, io\nfrom drivegain.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        f"    status = main({argv!r})\n"
        "assert status == 0, status"
    )
    assert _loaded_after(code) == []


def test_the_probe_sees_a_heavy_import() -> None:
    """The check can fail: importing the signal processing loads scipy.signal."""
    assert "scipy.signal" in _loaded_after("import drivegain.identify.signal")
