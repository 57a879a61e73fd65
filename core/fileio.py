"""Writing output files so that a reader never sees half of one and nothing is lost by mistake.

Every command that writes checks its output paths first (:func:`check_output`), before any
long computation or any motion, so a bad ``--out`` costs nothing; files are then written whole
through a temporary file and a rename (:func:`write_atomic`). Input files are read under
:func:`reading`, which turns the operating system's errors into one line naming the file.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from drivegain.errors import InputError


@contextmanager
def reading(
    path: str | Path, *, error: type[InputError] = InputError, expected: str = "a file"
) -> Iterator[None]:
    """Open and read ``path`` inside this block: a missing file, a directory, text that is not
    UTF-8 or any other operating-system error becomes ``error`` (one line naming the file).

    Parameters
    ----------
    path
        The file (a path or a storage location), as the message names it.
    error
        The :class:`~drivegain.errors.InputError` subclass raised.
    expected
        What the file should have been, for the directory message (e.g. ``"a CSV file"``).
    """
    try:
        yield
    except FileNotFoundError:
        raise error("file not found", file=path) from None
    except IsADirectoryError:
        raise error(f"is a directory, expected {expected}", file=path) from None
    except UnicodeDecodeError:
        raise error("not a UTF-8 text file", file=path) from None
    except OSError as exc:
        # remote file systems raise OSErrors without an errno: their text is the reason
        raise error(f"cannot read ({exc.strerror or exc})", file=path) from None


def check_output(
    path: str | Path,
    *,
    suffix: str | None = None,
    overwrite: bool = False,
    directory: bool = False,
    key: str = "--out",
) -> Path:
    """Refuse an output path that cannot or must not be written, before any work is done.

    Parameters
    ----------
    path
        The file (or, with ``directory``, the folder) to be written.
    suffix
        Required file name ending (e.g. ``".mcap"``), if any.
    overwrite
        Whether an existing file may be replaced. Recorded data (logs) never is.
    directory
        ``path`` is a folder to create or fill rather than a file.
    key
        The option named in the message.

    Returns
    -------
    Path
        ``path`` as a :class:`~pathlib.Path`.

    Raises
    ------
    InputError
        One line naming the path: wrong suffix, an existing file that must not be replaced, a
        directory where a file is expected (or the reverse), or a folder that cannot be written
        (missing folders are created later, as ``mkdir -p`` would).
    """
    p = Path(path)
    if not directory and p.is_dir():
        raise InputError("is a folder, expected a file name", file=p, key=key)
    if suffix is not None and not p.name.endswith(suffix):
        raise InputError(f"must end with {suffix}", file=p, key=key)
    if directory:
        if p.exists() and not p.is_dir():
            raise InputError("exists and is not a folder", file=p, key=key)
        parent = p if p.is_dir() else _existing_parent(p, key)
    else:
        if p.exists() and not overwrite:
            raise InputError("exists; refusing to overwrite it", file=p, key=key)
        parent = _existing_parent(p, key)
    try:  # a real probe: permission bits say nothing of a read-only mount, or for root
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as exc:
        raise InputError(
            f"folder {parent} is not writable ({exc.strerror})", file=p, key=key
        ) from None
    return p


def _existing_parent(p: Path, key: str = "--out") -> Path:
    """The nearest folder that exists above ``p`` (where ``mkdir -p`` would start)."""
    q = p.absolute().parent
    while not q.exists():
        q = q.parent
    if not q.is_dir():
        raise InputError(f"{q} is not a folder", file=p, key=key)
    return q


def write_atomic(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder, fsync and a
    rename: a reader sees the old file or the new one, never a part.

    Raises
    ------
    OSError
        From the file system (the temporary file is removed, ``path`` is untouched).
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        # mkstemp creates 0600; give the file the usual permissions (umask applied).
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)
    return path


def fsync_dir(directory: Path) -> None:
    """Make a rename or a new file in ``directory`` durable (best effort: some file systems
    refuse to fsync a folder, and the data itself is already synced)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
