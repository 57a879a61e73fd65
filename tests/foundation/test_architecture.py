"""The layout holds: imports run one way along the data flow, and no module holds two jobs.

Read from the source folders with :mod:`ast` (no import is executed), so a lazy import inside a
function counts as much as one at the top of a module.
"""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _folders() -> dict[str, str]:
    """Source folder → the subpackage name it is installed as (pyproject's package-dir)."""
    with (ROOT / "pyproject.toml").open("rb") as fh:
        dirs = tomllib.load(fh)["tool"]["setuptools"]["package-dir"]
    return {folder: pkg.removeprefix("drivegain").lstrip(".") for pkg, folder in dirs.items()}


FOLDERS = _folders()

#: What each folder may import (besides itself). core ← config ← dynamics/formats ← excite ←
#: drivers ← acquire, and identify ← dynamics/formats; acquire runs identify only for the demo,
#: the validation study sits on top of everything but acquire. The command line (core/cli.py)
#: reaches the commands through importlib by name, which is not an import statement.
ALLOWED = {
    "core": set(),
    "config": {"core"},
    "dynamics": {"core", "config"},
    "formats": {"core", "config"},
    "excite": {"core", "config", "dynamics", "formats"},
    "drivers": {"core", "config", "dynamics", "formats", "excite"},
    "identify": {"core", "config", "dynamics", "formats"},
    "acquire": {"core", "config", "dynamics", "formats", "excite", "drivers", "identify"},
    "validation": {"core", "config", "dynamics", "formats", "excite", "drivers", "identify"},
    "fleet": {"core", "config", "dynamics", "formats", "identify"},
}

#: Single modules allowed more than their folder: the command line declares every option, with
#: the defaults the config package declares once.
EXCEPTIONS = {"core/cli.py": {"config"}}

#: A module past this many lines is a sign that it holds two jobs (design.md).
MAX_LINES = 600

_BY_PACKAGE = {pkg: folder for folder, pkg in FOLDERS.items() if pkg}


def _imported_folders(source: str) -> set[str]:
    """Folders of the ``drivegain`` modules a module imports (any depth, any position)."""
    found = set()
    for node in ast.walk(ast.parse(source)):
        names: list[str] = []
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
            if node.module == "drivegain":
                names += [f"drivegain.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        for name in names:
            parts = name.split(".")
            if parts[0] != "drivegain":
                continue
            sub = parts[1] if len(parts) > 1 else ""
            found.add(_BY_PACKAGE.get(sub, "core"))
    return found


def import_violations(root: Path) -> list[str]:
    """``"file: imports folder"`` for every import against :data:`ALLOWED` below ``root``."""
    bad = []
    for folder, allowed in ALLOWED.items():
        for path in sorted((root / folder).rglob("*.py")):
            rel = path.relative_to(root).as_posix()
            extra = EXCEPTIONS.get(rel, set())
            for target in sorted(_imported_folders(path.read_text(encoding="utf-8"))):
                if target != folder and target not in allowed | extra:
                    bad.append(f"{rel}: imports {target}")
    return bad


def _modules() -> list[Path]:
    return sorted(p for folder in FOLDERS for p in (ROOT / folder).rglob("*.py"))


def test_every_folder_is_known_and_acyclic() -> None:
    assert set(ALLOWED) == set(FOLDERS)
    # The allowed graph itself has no cycle: a topological order exists.
    order: list[str] = []
    pending = dict(ALLOWED)
    while pending:
        ready = [f for f, deps in pending.items() if deps <= set(order)]
        assert ready, f"cycle among {sorted(pending)}"
        order += sorted(ready)
        for f in ready:
            del pending[f]


def test_imports_run_one_way() -> None:
    assert import_violations(ROOT) == []


def test_a_backward_import_is_caught(tmp_path: Path) -> None:
    for folder in FOLDERS:
        (tmp_path / folder).mkdir()
    (tmp_path / "excite" / "bad.py").write_text(
        "def f():\n    from drivegain.identify.pipeline import run_identify\n"
    )
    (tmp_path / "dynamics" / "also_bad.py").write_text("from drivegain import acquire\n")
    assert import_violations(tmp_path) == [
        "dynamics/also_bad.py: imports acquire",
        "excite/bad.py: imports identify",
    ]


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_module_holds_two_jobs(path: Path) -> None:
    lines = len(path.read_text(encoding="utf-8").splitlines())
    assert lines <= MAX_LINES, f"{path.relative_to(ROOT)}: {lines} lines"
