"""benchmarks/baseline.py: a commit installed in a temporary venv with no network, beside
this tree (issue 19). A tiny repository stands for the project, so the test takes seconds."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from baseline import BaselineInstall, measure

PYPROJECT = """[build-system]
requires = ["setuptools>=61"]
build-backend = "setuptools.build_meta"

[project]
name = "tinybench"
version = "{version}"

[project.scripts]
tinybench = "tinybench:main"
"""
MODULE = """import sys
VERSION = "{version}"
def main():
    print(VERSION)
    bytearray(40 * 1024 * 1024)  # 40 MB touched: the peak RSS must show it
    sys.exit(3)
"""


def _git(repo: Path, *args: str) -> str:
    env = {
        **os.environ,
        "GIT_AUTHOR_NAME": "t",
        "GIT_AUTHOR_EMAIL": "t@t",
        "GIT_COMMITTER_NAME": "t",
        "GIT_COMMITTER_EMAIL": "t@t",
    }
    out = subprocess.run(
        ["git", "-C", str(repo), *args], check=True, capture_output=True, text=True, env=env
    )
    return out.stdout.strip()


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_an_old_commit_is_installed_apart_and_offline(tmp_path: Path) -> None:
    repo = tmp_path / "repo"
    (repo / "tinybench").mkdir(parents=True)
    _git(repo, "init", "-q")
    commits = []
    for version in ("1.0", "2.0"):
        (repo / "pyproject.toml").write_text(PYPROJECT.format(version=version))
        (repo / "tinybench" / "__init__.py").write_text(MODULE.format(version=version))
        _git(repo, "add", "-A")
        _git(repo, "commit", "-q", "-m", version)
        commits.append(_git(repo, "rev-parse", "HEAD"))
    with BaselineInstall(commits[0], repo=repo) as base:
        # installed in the venv, not imported from the tree
        assert base.check("tinybench").startswith(str(base.venv))
        out = subprocess.run(base.command("tinybench"), capture_output=True, text=True)
        assert out.stdout.strip() == "1.0"  # the old commit, while the tree holds 2.0
        m = measure(base.command("tinybench"))
        assert m.status == 3 and m.peak_mb > 40 and m.wall_s > 0
        root = base.root
    assert not root.exists()
    assert _git(repo, "worktree", "list").count("\n") == 0  # the worktree was removed
