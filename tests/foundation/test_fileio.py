"""Output paths are checked before any work, and files are written whole."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivegain.errors import InputError
from drivegain.fileio import check_output, write_atomic


@pytest.fixture
def read_only_folder(tmp_path: Path) -> Iterator[Path]:
    """A folder nobody can create files in (root ignores permission bits: use /sys then)."""
    if os.geteuid() != 0:
        d = tmp_path / "ro"
        d.mkdir()
        d.chmod(0o555)
        yield d
        d.chmod(0o755)
        return
    d = Path("/sys/fs")
    try:
        (d / ".drivegain-probe").touch()
    except OSError:
        yield d
        return
    pytest.skip("no folder here refuses new files to root")


def test_refusals_name_the_path(tmp_path: Path, read_only_folder: Path) -> None:
    existing = tmp_path / "run.mcap"
    existing.write_bytes(b"recorded")
    cases = [
        (dict(path=existing, suffix=".mcap"), "refusing to overwrite"),
        (dict(path=tmp_path / "x.txt", suffix=".mcap"), "must end with .mcap"),
        (dict(path=tmp_path), "is a folder"),
        (dict(path=existing, directory=True), "exists and is not a folder"),
        (dict(path=existing / "sub" / "f.json"), "is not a folder"),
        (dict(path=read_only_folder / "f.json"), "is not writable"),
        (dict(path=read_only_folder / "new" / "report", directory=True), "is not writable"),
    ]
    for kwargs, fragment in cases:
        with pytest.raises(InputError) as exc:
            check_output(**kwargs)  # type: ignore[arg-type]
        text = str(exc.value)
        assert fragment in text and str(kwargs["path"]) in text and "\n" not in text
    assert existing.read_bytes() == b"recorded"


def test_what_may_be_written_passes(tmp_path: Path) -> None:
    (tmp_path / "old.json").write_text("{}")
    assert check_output(tmp_path / "old.json", overwrite=True) == tmp_path / "old.json"
    assert check_output(tmp_path / "a" / "b" / "new.mcap", suffix=".mcap")
    assert check_output(tmp_path / "a" / "report", directory=True)
    assert check_output(tmp_path, directory=True) == tmp_path
    assert list(tmp_path.iterdir()) == [tmp_path / "old.json"]  # nothing created by a check


def test_write_atomic_replaces_whole_and_leaves_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "sub" / "f.bin"
    write_atomic(target, b"one")
    write_atomic(target, b"two")
    assert target.read_bytes() == b"two"
    assert [p.name for p in target.parent.iterdir()] == ["f.bin"]
