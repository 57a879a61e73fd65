"""Inputs and outputs of a batch through fsspec: local folders by default, any URL fsspec knows.

A location is a string: a local path (``results``, ``/data/fleet``) or a URL (``file://...``,
``s3://bucket/fleet`` when the ``s3fs`` backend is installed). Identification reads local files,
so a remote input is copied into a temporary folder first; its outputs are written locally and
then put in place. Every result file is written under a temporary name and moved onto its final
name, so a reader (or a re-run) sees either the whole file or none.
"""

from __future__ import annotations

import posixpath
import uuid
from pathlib import Path
from typing import Any

import fsspec
from fsspec.implementations.local import LocalFileSystem

from drivegain.errors import InputError
from drivegain.fileio import reading


def filesystem(location: str) -> tuple[Any, str]:
    """The fsspec file system of ``location`` and the path inside it.

    Raises
    ------
    InputError
        No fsspec backend for the URL's protocol (names the location).
    """
    try:
        fs, path = fsspec.core.url_to_fs(location)
    except (ImportError, ValueError) as exc:
        raise InputError(f"no file system for this location ({exc})", file=location) from None
    return fs, path


def is_local(location: str) -> bool:
    """Whether ``location`` is on the local file system."""
    return isinstance(filesystem(location)[0], LocalFileSystem)


def join(base: str, *parts: str) -> str:
    """``base`` joined with ``parts`` with forward slashes (URLs keep their protocol)."""
    return posixpath.join(base.rstrip("/"), *parts) if parts else base


def resolve(location: str, relative_to: str | None) -> str:
    """``location``, relative to the folder ``relative_to`` when it is a relative local path."""
    if "://" in location or relative_to is None or Path(location).is_absolute():
        return location
    if "://" in relative_to:
        return join(relative_to, location)
    return str(Path(relative_to) / location)


def parent(location: str) -> str:
    """The folder holding ``location``."""
    if "://" in location:
        return posixpath.dirname(location.rstrip("/"))
    return str(Path(location).resolve().parent)


def exists(location: str) -> bool:
    """Whether a file or folder exists at ``location``."""
    fs, path = filesystem(location)
    return bool(fs.exists(path))


def read_bytes(location: str) -> bytes:
    """The content of the file at ``location``.

    Raises
    ------
    InputError
        The file does not exist or cannot be read (names it).
    """
    fs, path = filesystem(location)
    with reading(location), fs.open(path, "rb") as fh:
        return bytes(fh.read())


#: Ending of the temporary names :func:`write_atomic` writes under (``.NAME.HEX.part``).
PART_SUFFIX = ".part"


def _is_part(name: str) -> bool:
    """Whether ``name`` is one :func:`write_atomic` gives its temporary files."""
    return name.startswith(".") and name.endswith(PART_SUFFIX)


def write_atomic(location: str, data: bytes) -> None:
    """Write ``data`` to ``location``: under a temporary name, then moved onto the final name.

    On a local disk the move is a rename (atomic); on object storage an object appears whole
    when its upload finishes, so the move (copy + delete) never shows a partial file either.
    """
    fs, path = filesystem(location)
    folder = posixpath.dirname(path)
    if folder:
        fs.makedirs(folder, exist_ok=True)
    tmp = posixpath.join(folder, f".{posixpath.basename(path)}.{uuid.uuid4().hex}{PART_SUFFIX}")
    try:
        with fs.open(tmp, "wb") as fh:
            fh.write(data)
        fs.mv(tmp, path)
    except BaseException:
        if fs.exists(tmp):
            fs.rm(tmp)
        raise


def remove_stale_parts(location: str) -> list[str]:
    """Delete the temporary files :func:`write_atomic` left below ``location``, return them.

    A worker killed between opening and moving its temporary file leaves it behind; the task
    that runs again in its place calls this first, so the results folder holds only whole
    files. Only names :func:`write_atomic` gives (``.NAME.HEX.part``) are touched.
    """
    fs, path = filesystem(location)
    if not fs.exists(path):
        return []
    stale = [p for p in fs.find(path) if _is_part(posixpath.basename(p))]
    for p in stale:
        fs.rm(p)
    return stale


def put_file(local: Path, location: str) -> None:
    """Copy the local file ``local`` to ``location`` (atomically, as :func:`write_atomic`)."""
    write_atomic(location, local.read_bytes())


def local_copy(location: str, folder: Path) -> Path:
    """A local path holding the file at ``location``: itself when local, else a copy in
    ``folder``.

    Raises
    ------
    InputError
        The file does not exist (names it).
    """
    fs, path = filesystem(location)
    if isinstance(fs, LocalFileSystem):
        p = Path(path)
        if not p.is_file():
            raise InputError("file not found", file=location)
        return p
    target = folder / f"{uuid.uuid4().hex[:8]}-{posixpath.basename(path)}"
    target.write_bytes(read_bytes(location))
    return target


def glob(pattern: str) -> list[str]:
    """Files matching ``pattern`` (fsspec glob, ``**`` recursive), as locations, sorted."""
    fs, path = filesystem(pattern)
    found = sorted(fs.glob(path))
    if isinstance(fs, LocalFileSystem):
        return found
    return [fs.unstrip_protocol(p) for p in found]


def listing(folder: str, suffix: str) -> list[str]:
    """Files below ``folder`` (any depth) whose name ends with ``suffix``, as locations."""
    return glob(join(folder, "**", f"*{suffix}"))
