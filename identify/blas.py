"""Limit the threads of the OpenBLAS libraries bundled with numpy and scipy, for a while.

Identification does many LAPACK calls on small matrices (QR and SVD of ~80 columns). OpenBLAS
threads them; on a machine whose cores are busy with other work, every call then waits for its
threads to be scheduled, which was measured here to make those calls 10 to 25 times slower
(a 1000×77 QR: 37 ms instead of 1.4 ms). One thread is never much slower for these sizes.

There is no numpy API for this; the OpenBLAS entry points are called through ctypes, as
threadpoolctl does. When a library or symbol cannot be found, nothing happens.
"""

from __future__ import annotations

import ctypes
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

_NAMES = (
    ("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
    ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"),
    ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
    ("openblas_set_num_threads", "openblas_get_num_threads"),
)


def _loaded_openblas() -> list[str]:
    """Paths of the OpenBLAS shared libraries mapped into this process (Linux)."""
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        return []
    paths = []
    for line in maps.splitlines():
        parts = line.split()
        if len(parts) >= 6 and "openblas" in Path(parts[5]).name and parts[5] not in paths:
            paths.append(parts[5])
    return paths


def _controls() -> list[tuple[Any, Any]]:
    out = []
    for path in _loaded_openblas():
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for set_name, get_name in _NAMES:
            setter = getattr(lib, set_name, None)
            getter = getattr(lib, get_name, None)
            if setter is not None and getter is not None:
                setter.argtypes, setter.restype = [ctypes.c_int], None
                getter.argtypes, getter.restype = [], ctypes.c_int
                out.append((setter, getter))
                break
    return out


@contextmanager
def limited_blas_threads(threads: int = 1) -> Iterator[None]:
    """Run the body with at most ``threads`` OpenBLAS threads, then restore the old counts."""
    import numpy  # noqa: F401  (load numpy's OpenBLAS so it can be found)
    import scipy.linalg  # noqa: F401  (and scipy's)

    controls = _controls()
    previous = [getter() for _, getter in controls]
    for setter, _ in controls:
        setter(threads)
    try:
        yield
    finally:
        for (setter, _), n in zip(controls, previous, strict=True):
            setter(n)
