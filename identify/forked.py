"""Independent work in a forked child process while this process goes on.

Two parts of an identification of long recordings do not depend on each other's results: the
Case 1 fit and the gains' estimation, then the other friction form's fits and the validation
and cross-validation of the chosen one. On two cores each pair takes the time of the longer
part when one of them runs in a forked child. The child inherits the prepared data (nothing is
copied until written) and sends back its small result, pickled, over a pipe.

Where a fork is not safe (no ``fork`` start method, other threads running, whose locks the child
would inherit in any state), only one CPU is ours, or the work is too small to pay for the fork,
the function runs here, at once, in the same order as before. Both ways run the same function on
the same data, so the results are identical.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from typing import Any, Generic, TypeVar

from drivegain.errors import IdentificationError
from drivegain.identify.blas import limited_blas_threads

T = TypeVar("T")
U = TypeVar("U")

#: Scalar-equation count (samples × joints of the runs) from which independent work on long runs
#: goes to a forked child: below it a fork and the pickled results cost more than they save
#: (one 60 s run at 250 Hz, decimated, is about 1 500 samples).
PARALLEL_EQUATIONS = 120_000


def fork_is_safe() -> bool:
    """Whether a child may be forked here: ``fork`` exists, no other thread runs (a fork
    copies other threads' locks in whatever state they are: the child could deadlock) and this
    is not itself a forked child (a daemonic process may not have children, and the CPU its
    child would use is the parent's)."""
    if "fork" not in multiprocessing.get_all_start_methods():
        return False
    if multiprocessing.current_process().daemon:
        return False
    return threading.active_count() == 1


def two_cpus() -> bool:
    """Whether at least two CPUs are ours (else a child only takes turns with this process)."""
    return len(os.sched_getaffinity(0)) > 1


def send_error(conn: Connection, exc: BaseException) -> None:
    """Send ``("error", exc)`` to the parent; an exception that does not pickle goes as an
    :class:`IdentificationError` with its type and line."""
    try:
        conn.send(("error", exc))
    except Exception:
        conn.send(("error", IdentificationError(f"{type(exc).__name__}: {exc}")))


def _child(conn: Connection, fn: Callable[[], Any]) -> None:
    """The child's whole life: ``fn()`` run and its result (or exception) sent back."""
    try:
        with limited_blas_threads(1):  # the parent uses the other CPU
            result = fn()
        conn.send(("done", result))
    except BaseException as exc:
        send_error(conn, exc)
    finally:
        conn.close()


class Pending(Generic[T]):
    """The result of ``fn``, computed in a forked child or already here.

    Use :func:`start`; :meth:`result` waits for the child and returns its result or raises its
    exception; :meth:`cancel` ends a child whose result is no longer wanted.
    """

    def __init__(self, what: str, fn: Callable[[], T], fork: bool):
        self._what = what
        self._proc: Any = None
        self._conn: Connection | None = None
        self._value: T | None = None
        if not fork:
            self._value = fn()
            return
        ctx = multiprocessing.get_context("fork")
        ours, theirs = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(
            target=_child, args=(theirs, fn), name=f"drivegain-{what}", daemon=True
        )
        self._proc.start()
        theirs.close()
        self._conn = ours

    @property
    def forked(self) -> bool:
        """Whether the work runs (or ran) in a child process."""
        return self._proc is not None

    def result(self) -> T:
        """The function's result; its exception re-raised here.

        Raises
        ------
        IdentificationError
            The child ended without an answer (killed, out of memory).
        """
        if self._conn is None:
            return self._value  # type: ignore[return-value]  # computed here, at start
        try:
            kind, payload = self._conn.recv()
        except EOFError:
            raise IdentificationError(
                f"{self._what}: the process computing it ended without an answer"
            ) from None
        finally:
            self._close()
        if kind == "error":
            raise payload
        self._value = payload
        return payload

    def cancel(self) -> None:
        """End the child (if any) without waiting for its result."""
        if self._proc is not None and self._proc.is_alive():
            self._proc.kill()  # nothing to clean up; a SIGTERM handler inherited could ignore it
        self._close()

    def _close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._proc is not None:
            self._proc.join()


def start(what: str, fn: Callable[[], T], *, parallel: bool) -> Pending[T]:
    """Run ``fn`` in a forked child when ``parallel`` and a fork is safe, else here at once.

    Parameters
    ----------
    what
        What ``fn`` computes, for the process name and error messages.
    fn
        The work: no arguments (a closure over the data), a picklable result.
    parallel
        The caller's judgement that the work is large enough to pay for a fork (tens of ms).
    """
    return Pending(what, fn, fork=parallel and two_cpus() and fork_is_safe())


def map_items(what: str, fn: Callable[[U], T], items: Sequence[U], *, parallel: bool) -> list[T]:
    """``[fn(x) for x in items]``, the first item in a forked child (:func:`start`) while the
    others run here, in turn; the child is ended if the work here fails.

    For the same work on each of a few long runs: on two cores the list takes the time of the
    longest item instead of the sum. Results are in ``items``' order either way.
    """
    if not items:
        return []
    first = start(what, lambda: fn(items[0]), parallel=parallel and len(items) > 1)
    try:
        rest = [fn(x) for x in items[1:]]
    except BaseException:
        first.cancel()
        raise
    return [first.result(), *rest]
