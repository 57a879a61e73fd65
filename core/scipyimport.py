"""Importing SciPy submodules without the cost of SciPy's docstring rewriting.

Since SciPy 1.15, each function decorated with ``xp_capabilities`` (hundreds in
``scipy.signal`` and ``scipy.stats``) has its docstring parsed and rebuilt at import time, only
to add a table of array-API backends to its Notes. On the 2-core machines of issue 19 that was
more than half of ``import scipy.signal`` (1.4 s of 3.4 s when busy) and the largest single
cost of a short ``drivegain identify``. :func:`import_scipy` imports a submodule with that
docstring step replaced by one that keeps the docstring as written: the functions, their
capability records and every result are unchanged; only the added Notes table is missing from
``help()``.

The replaced name is private to SciPy: when it is absent (another SciPy version) the import is
done the ordinary way.
"""

from __future__ import annotations

import importlib
import sys
import threading
from types import ModuleType
from typing import Any

_LOCK = threading.Lock()


class _KeptDoc:
    """Stands for ``scipy._lib._docscrape.FunctionDoc``: sections read empty, edits are
    dropped, and ``str`` gives back the function's own docstring (after a signature line,
    which the caller strips)."""

    def __init__(self, func: Any, *args: Any, **kwargs: Any) -> None:
        self._doc = getattr(func, "__doc__", None) or ""
        self._sections: dict[str, list[Any]] = {}

    def __getitem__(self, key: str) -> list[Any]:
        return self._sections.setdefault(key, [])

    def __setitem__(self, key: str, value: Any) -> None:
        self._sections[key] = value

    def __str__(self) -> str:
        return "\n" + self._doc


def import_scipy(name: str) -> ModuleType:
    """``importlib.import_module(name)`` for a SciPy submodule, without the docstring rewrite.

    Parameters
    ----------
    name
        Dotted module name, e.g. ``"scipy.signal"``.
    """
    if name in sys.modules:
        return sys.modules[name]
    with _LOCK:
        try:
            docscrape = importlib.import_module("scipy._lib._docscrape")
            original = docscrape.FunctionDoc
        except (ImportError, AttributeError):
            return importlib.import_module(name)
        # The decorators look the name up in their own modules (bound by ``from ... import``),
        # so it is replaced wherever it is bound, and put back everywhere afterwards, in the
        # modules this import loaded too.
        for module in _scipy_modules():
            if getattr(module, "FunctionDoc", None) is original:
                setattr(module, "FunctionDoc", _KeptDoc)  # noqa: B010
        try:
            return importlib.import_module(name)
        finally:
            for module in _scipy_modules():
                if getattr(module, "FunctionDoc", None) is _KeptDoc:
                    setattr(module, "FunctionDoc", original)  # noqa: B010


def _scipy_modules() -> list[ModuleType]:
    return [
        m
        for key, m in list(sys.modules.items())
        if (key == "scipy" or key.startswith("scipy.")) and isinstance(m, ModuleType)
    ]
