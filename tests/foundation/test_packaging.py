"""The distribution: every module is in the wheel, and the namespace does not shadow PyPI names."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest


def _components() -> dict[str, str]:
    """Source folder → its path in the wheel, from pyproject's package-dir (one declaration)."""
    root = Path(__file__).resolve().parents[2]
    with (root / "pyproject.toml").open("rb") as fh:
        dirs = tomllib.load(fh)["tool"]["setuptools"]["package-dir"]
    return {folder: pkg.replace(".", "/") for pkg, folder in dirs.items()}


COMPONENTS = _components()


@pytest.fixture(scope="module")
def wheel(repo_root: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("build")
    out = tmp_path_factory.mktemp("wheel")
    src = tmp_path_factory.mktemp("src") / "drivegain"
    # Build from a copy so the checkout is not touched (build/ and egg-info stay out of it).
    shutil.copytree(
        repo_root,
        src,
        ignore=shutil.ignore_patterns(".venv*", ".git", "build", "*.egg-info", "__pycache__",
                                      "drivegain-demo", ".mypy_cache", ".ruff_cache",
                                      ".pytest_cache"),
    )  # fmt: skip
    subprocess.run(
        [
            sys.executable,
            "-m",
            "build",
            "--wheel",
            "--no-isolation",
            "--outdir",
            str(out),
            str(src),
        ],
        check=True,
        capture_output=True,
    )
    (whl,) = out.glob("drivegain-*.whl")
    return whl


def test_wheel_contains_every_module(wheel: Path, repo_root: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = []
    for folder, target in COMPONENTS.items():
        for f in (repo_root / folder).rglob("*"):
            if "__pycache__" in f.parts or not f.is_file():
                continue
            if f.suffix in {".py", ".toml", ".eds", ".json", ".typed", ".service"}:
                rel = f.relative_to(repo_root / folder).as_posix()
                if f"{target}/{rel}" not in names:
                    missing.append(f"{folder}/{rel}")
    assert not missing, f"not in the wheel: {missing}"


def test_import_identify_is_not_ours(tmp_path: Path) -> None:
    """With the PyPI package `identify` present, `import identify` must give it, not us."""
    fake = tmp_path / "site" / "identify"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("ORIGIN = 'pypi'\n")
    code = (
        "import sys; sys.path.append(sys.argv[1]);"
        "import identify, drivegain.identify;"
        "print(getattr(identify, 'ORIGIN', identify.__file__));"
        "print(drivegain.identify.__name__)"
    )
    res = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path / "site")],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        check=True,
    )
    assert res.stdout.split() == ["pypi", "drivegain.identify"]
