"""The inverse dynamic identification model (IDIM) regressor, for many samples at once.

``tau = W(q, qd, qdd) @ chi`` with ``chi`` the standard parameters of :mod:`.params`.

How it is computed, and why this way: the regressor entry of joint i and link j (j >= i) is the
unit screw of joint i, expressed in frame j, dotted with the wrench regressor of link j in its own
frame (Newton-Euler, first moments about the frame origin). Written per sample with 3x3 matrices
this is dominated by numpy's per-call overhead on tiny arrays, so the recursion is instead *traced
once per model* on scalar fields (struct of arrays: one 1-D array per scalar, over a chunk of
samples). The trace folds every constant of the kinematics (MDH rotations by ±π/2 become signed
permutations, zero offsets vanish, constant gravity in the first frames stays a number), keeps
signs and constant factors symbolic, and shares common products. What remains is a flat list of
elementwise numpy operations on rows of a work array, executed chunk by chunk, each operation
that produces an output entry writing it straight into the output. The output is stored
sample-last, (n, p, N), and returned as an (N, n, p) view of it: one entry over a chunk of samples
is then one contiguous stretch of memory, and the many structurally zero entries are never
touched (whole runs of them, such as a joint's row for the links before it, are pages the
operating system never has to hand out). Rotor inertia, friction, offsets and the coupled-motor
terms are traced the same way. For large N about half the time is the arithmetic and half the
fresh output memory; see benchmarks/bench_regressor.py.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable
from typing import Any, Literal

import numpy as np

from drivegain.config.robot import WristFriction
from drivegain.dynamics.model import RobotModel
from drivegain.dynamics.params import N_INERTIAL, N_PER_JOINT, n_standard
from drivegain.dynamics.tracing import UFUNC, UNARY, Op, Program, Sym, trace_program
from drivegain.errors import InputError

#: Samples per pass of the traced program: amortises numpy's per-call overhead (about 0.4 µs
#: for each of the ~930 operations of the TX-40) while the ~70 work rows stay near L2 size.
#: Measured for 20 000 samples (best/median of 9, µs per sample): 2048 → 1.24/1.34,
#: 4096 → 0.92-0.98/1.05, 8192 → 1.05-1.11/1.13-1.15, 16384 → 1.01-1.08/1.08-1.11.
CHUNK = 4096
_MIN_CHUNK = 16
_Layout = Literal["standard", "rigid"]


def _entries(model: RobotModel, prog: Program, layout: _Layout) -> tuple[int, dict[int, Sym]]:
    """Output width p and the non-zero entries, by flat index ``row·p + column``."""
    n = model.n
    if layout == "rigid":
        p = N_INERTIAL * n
        flat = {i * p + N_INERTIAL * j + k: s for (i, j, k), s in prog.rigid.items()}
    else:
        p = n_standard(model.robot)
        flat = {i * p + N_PER_JOINT * j + k: s for (i, j, k), s in prog.rigid.items()}
        flat.update({i * p + c: s for (i, c), s in prog.extra.items()})
    return p, {k: s for k, s in flat.items() if s.coef != 0.0}


_BINARY = frozenset({"mul", "add", "sub"})
#: Padding of each work row, elements (see _Kernel).
_ROW_PAD = 16


def _sources(op: Op) -> tuple[int, ...]:
    kind, a, b = op
    return (a, int(b)) if kind in _BINARY else (a,)  # type: ignore[arg-type]


#: An operand of a planned operation: ("w", work row), ("o", output entry) or ("c", number).
_Arg = tuple[str, "int | float"]


def _sin_cos(q: np.ndarray, sin: np.ndarray, cos: np.ndarray) -> None:
    """``sin q`` and ``cos q`` from ``t = tan(q/2)``; ``q`` is overwritten.

    numpy's float64 sine and cosine are scalar library calls (about 10 ns each here), its tangent
    is vectorised (about 1.4 ns): with ``sin q = 2t/(1+t²)`` and ``cos q = (1-t²)/(1+t²)`` this
    is five times faster, and within 2.3e-16 of ``np.sin``/``np.cos`` (tested from -4.8 to 4.8
    rad and at ±π, where ``t`` is large but finite).
    """
    np.multiply(q, 0.5, out=sin)
    np.tan(sin, out=sin)
    np.multiply(sin, sin, out=cos)
    np.add(cos, 1.0, out=q)
    np.divide(1.0, q, out=q)
    np.subtract(1.0, cos, out=cos)
    np.multiply(cos, q, out=cos)
    np.multiply(q, 2.0, out=q)
    np.multiply(sin, q, out=sin)


class _Kernel:
    """A program laid out on the rows of one work array, for chunks of ``chunk`` samples.

    Work rows: ``q, sin q, cos q, qd, qdd`` (n each), then temporaries (reused once dead). Every
    non-zero output entry is written by its operation straight into the output, which is stored
    sample-last (see :meth:`run`): one entry over a chunk of samples is a contiguous stretch of
    memory, so no transposing copy is needed and zero entries are never touched.
    """

    def __init__(self, model: RobotModel, prog: Program, layout: _Layout, chunk: int) -> None:
        n, n_in, ops = prog.n, 4 * prog.n, list(prog.ops)
        self.n, self.chunk, self.lock = n, chunk, threading.Lock()
        p, entries = _entries(model, prog, layout)
        self.p = p

        # Dead-code elimination; count the readers of each slot.
        readers: dict[int, int] = {}
        for sym in entries.values():
            if sym.slot >= 0:
                readers[sym.slot] = readers.get(sym.slot, 0) + 1
        live = set(readers)
        for k in range(len(ops) - 1, -1, -1):
            if n_in + k in live:
                for src in _sources(ops[k]):
                    live.add(src)
                    readers[src] = readers.get(src, 0) + 1

        # Output entry e (= joint row·p + column) is row e of the output. An op whose result is
        # an entry writes it in place when it can; otherwise a copy (or negation, or scaling)
        # follows the op.
        self.const_rows: list[tuple[int, float]] = []
        redirect: dict[int, int] = {}  # op slot -> output row it writes directly
        after: dict[int, list[tuple[Op, int]]] = {}  # slot -> final ops reading it
        for e, sym in sorted(entries.items()):
            if sym.slot < 0:
                self.const_rows.append((e, sym.coef))
                continue
            k = sym.slot - n_in
            if k >= 0 and sym.slot not in redirect:
                kind, a, b = ops[k]
                if sym.coef == 1.0:
                    redirect[sym.slot] = e
                    continue
                if readers[sym.slot] == 1 and sym.coef == -1.0 and kind == "sub":
                    ops[k] = ("sub", int(b), a)  # type: ignore[arg-type]
                    redirect[sym.slot] = e
                    continue
                if readers[sym.slot] == 1 and kind == "muls":
                    ops[k] = ("muls", a, float(b) * sym.coef)  # type: ignore[arg-type]
                    redirect[sym.slot] = e
                    continue
            if sym.coef == 1.0:
                final: Op = ("copy", sym.slot, None)
            elif sym.coef == -1.0:
                final = ("neg", sym.slot, None)
            else:
                final = ("muls", sym.slot, sym.coef)
            after.setdefault(sym.slot, []).append((final, e))

        # Execution order: finals on inputs first, then each live op followed by its finals.
        seq: list[tuple[Op, int, int]] = []  # (op, result slot or -1, output row or -1)
        for slot in range(n_in):
            seq += [(op, -1, e) for op, e in after.get(slot, [])]
        for k, op in enumerate(ops):
            slot = n_in + k
            if slot in live:
                seq.append((op, slot, redirect.get(slot, -1)))
                seq += [(fop, -1, e) for fop, e in after.get(slot, [])]
        last_use: dict[int, int] = {}
        for idx, (op, _, _) in enumerate(seq):
            for src in _sources(op):
                last_use[src] = idx

        # Register allocation (linear scan) of the work rows.
        row_of: dict[int, _Arg] = {slot: ("w", n + slot) for slot in range(n_in)}  # 0..n-1: q
        free: list[int] = []
        n_rows = 5 * n
        #: (ufunc, operands with the destination last)
        self.plan: list[tuple[Callable[..., Any], tuple[_Arg, ...]]] = []
        for idx, (op, slot, e) in enumerate(seq):
            kind, _, b = op
            args = [row_of[x] for x in _sources(op)]
            for x in set(_sources(op)):
                if x >= n_in and last_use[x] == idx and x not in redirect:
                    free.append(int(row_of[x][1]))
            dst: _Arg
            if e >= 0:
                dst = ("o", e)
            elif free:
                dst = ("w", free.pop())
            else:
                dst, n_rows = ("w", n_rows), n_rows + 1
            if slot >= 0:
                row_of[slot] = dst
            if kind not in _BINARY and kind not in UNARY:
                args.append(("c", float(b)))  # type: ignore[arg-type]
            self.plan.append((UFUNC[kind], (*args, dst)))
        self.n_rows = n_rows
        # Rows padded by two cache lines: with a power-of-two stride the rows an operation reads
        # and writes fall in the same cache sets (measured 4-6 % slower when timed alone).
        self.work = np.zeros((n_rows, chunk + _ROW_PAD))[:, :chunk]
        self.n_temp = n_rows - 5 * n
        self._full: tuple[list[tuple[Callable[..., Any], list[Any]]], list[Any]] | None = None
        #: The last partial chunk's binding, by width: callers tend to repeat their sample
        #: count, and binding takes about 0.9 ms (0.04 µs per sample of 20 000).
        self._part: tuple[int, tuple[list[tuple[Callable[..., Any], list[Any]]], list[Any]]] = (
            0,
            ([], []),
        )

    def bind(self, m: int) -> tuple[list[tuple[Callable[..., Any], list[Any]]], list[Any]]:
        """The operations on the first ``m`` work columns, and where output views go.

        Returns ``(ops, sites)``: each op a ufunc and its argument list (output operands left
        as None), and ``sites`` as ``(argument list, position, entry)`` to fill per chunk.
        """
        work = self.work[:, :m]
        ops: list[tuple[Callable[..., Any], list[Any]]] = []
        sites: list[Any] = []
        for f, spec in self.plan:
            args: list[Any] = []
            for pos, (where, v) in enumerate(spec):
                if where == "w":
                    args.append(work[int(v)])
                elif where == "c":
                    args.append(v)
                else:
                    args.append(None)
                    sites.append((args, pos, int(v)))
            ops.append((f, args))
        return ops, sites

    def run(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, out: np.ndarray) -> None:
        """Fill ``out`` (n·p, N), zero-initialised, with the entries for ``q, qd, qdd`` (N, n).

        Row ``i·p + c`` of ``out`` is the entry of joint ``i`` and column ``c`` for every sample.
        """
        n, chunk, work = self.n, self.chunk, self.work
        q_rows, sin_rows, cos_rows = work[0:n], work[n : 2 * n], work[2 * n : 3 * n]
        qd_rows, qdd_rows = work[3 * n : 4 * n], work[4 * n : 5 * n]
        for e, value in self.const_rows:
            out[e] = value
        if self._full is None:
            self._full = self.bind(chunk)
        try:
            for c0 in range(0, q.shape[0], chunk):
                m = min(chunk, q.shape[0] - c0)
                if m == chunk:
                    ops, sites = self._full
                else:
                    if self._part[0] != m:
                        self._part = (m, self.bind(m))
                    ops, sites = self._part[1]
                block = out[:, c0 : c0 + m]
                for args, pos, e in sites:
                    args[pos] = block[e]
                q_rows[:, :m] = q[c0 : c0 + m].T
                qd_rows[:, :m] = qd[c0 : c0 + m].T
                qdd_rows[:, :m] = qdd[c0 : c0 + m].T
                _sin_cos(q_rows[:, :m], sin_rows[:, :m], cos_rows[:, :m])
                for f, args in ops:
                    f(*args)
        finally:
            for args, pos, _ in (*self._full[1], *self._part[1][1]):
                args[pos] = None  # drop the views: they would keep ``out`` alive


_CACHE: dict[int, tuple[weakref.ref[RobotModel], dict[tuple[Any, ...], Any]]] = {}
_CACHE_LOCK = threading.Lock()


def _model_cache(model: RobotModel) -> dict[tuple[Any, ...], Any]:
    key = id(model)
    with _CACHE_LOCK:
        hit = _CACHE.get(key)
        if hit is not None and hit[0]() is model:
            return hit[1]
        store: dict[tuple[Any, ...], Any] = {}
        _CACHE[key] = (weakref.ref(model), store)
        weakref.finalize(model, _CACHE.pop, key, None)
        return store


def _program(model: RobotModel, form: WristFriction) -> Program:
    store = _model_cache(model)
    with _CACHE_LOCK:
        prog = store.get(("program", form))
    if prog is None:
        prog = trace_program(model, form)
        with _CACHE_LOCK:
            store[("program", form)] = prog
    return prog


def _kernel(model: RobotModel, form: WristFriction, layout: _Layout, samples: int) -> _Kernel:
    chunk = min(CHUNK, max(_MIN_CHUNK, 1 << max(0, samples - 1).bit_length()))
    store = _model_cache(model)
    key = ("kernel", form, layout, chunk)
    with _CACHE_LOCK:
        kern = store.get(key)
    if kern is None:
        kern = _Kernel(model, _program(model, form), layout, chunk)
        with _CACHE_LOCK:
            store[key] = kern
    return kern


def _run(
    model: RobotModel,
    form: WristFriction,
    layout: _Layout,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
) -> np.ndarray:
    n = model.n
    q, qd, qdd = (_as_samples(x, n, nm) for x, nm in ((q, "q"), (qd, "qd"), (qdd, "qdd")))
    if not q.shape[0] == qd.shape[0] == qdd.shape[0]:
        raise InputError(
            f"q, qd and qdd must have the same number of samples, got "
            f"{q.shape[0]}, {qd.shape[0]}, {qdd.shape[0]}"
        )
    kern = _kernel(model, form, layout, q.shape[0])
    # Stored sample-last, (n, p, N), returned as an (N, n, p) view: see standard_regressor.
    store = np.zeros((n, kern.p, q.shape[0]))
    if q.shape[0] > 0:
        flat = store.reshape(n * kern.p, q.shape[0])
        if kern.lock.acquire(blocking=False):
            try:
                kern.run(q, qd, qdd, flat)
            finally:
                kern.lock.release()
        else:  # another thread is using the cached work array: use a private one
            _Kernel(model, _program(model, form), layout, kern.chunk).run(q, qd, qdd, flat)
    return store.transpose(2, 0, 1)


def _as_samples(x: np.ndarray, n: int, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim == 1:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != n:
        raise InputError(f"{name} must have shape (samples, {n}), got {np.shape(x)}")
    return a


# --------------------------------------------------------------------------- public API


def rigid_body_regressor(
    model: RobotModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray
) -> np.ndarray:
    """Rigid-body joint torque regressor.

    Parameters
    ----------
    model
        The robot model.
    q, qd, qdd
        Joint positions (rad), velocities (rad/s), accelerations (rad/s²), shape (N, n) (or (n,)
        for one sample).

    Returns
    -------
    numpy.ndarray
        Shape (N, n, 10·n): torque of joint i (N·m) per inertial parameter
        ``[XX XY XZ YY YZ ZZ MX MY MZ M]`` of each link j, at the origin of frame j. Stored
        sample-last like :func:`standard_regressor`.
    """
    return _run(model, WristFriction(model.robot.wrist_friction), "rigid", q, qd, qdd)


def standard_regressor(
    model: RobotModel,
    q: np.ndarray,
    qd: np.ndarray,
    qdd: np.ndarray,
    wrist_friction: WristFriction | str | None = None,
) -> np.ndarray:
    """IDIM regressor on the standard parameters (see :mod:`drivegain.dynamics.params`).

    Parameters
    ----------
    model
        The robot model.
    q, qd, qdd
        Joint positions (rad, controller convention), velocities (rad/s), accelerations (rad/s²),
        shape (N, n) (or (n,) for one sample).
    wrist_friction
        Friction form of coupled motors; default: the robot file's choice.

    Returns
    -------
    numpy.ndarray
        Shape (N, n, n_standard): joint torques (N·m) per standard parameter. A view of an array
        stored sample-last, (n, n_standard, N): fast to filter or decimate along the samples; use
        ``np.ascontiguousarray`` where a sample-major C-ordered copy is wanted.
    """
    form = WristFriction(wrist_friction or model.robot.wrist_friction)
    return _run(model, form, "standard", q, qd, qdd)


def payload_columns(model: RobotModel, link: int) -> slice:
    """Standard-regressor columns whose torques a payload on ``link`` (1-based) produces."""
    base = N_PER_JOINT * (link - 1)
    return slice(base, base + N_INERTIAL)


def stack_joint_major(x: np.ndarray) -> np.ndarray:
    """Stack per-sample rows joint by joint: (N, n) -> (n·N,) or (N, n, p) -> (n·N, p)."""
    a = np.asarray(x)
    if a.ndim == 2:
        return a.T.reshape(-1)
    if a.ndim == 3:
        return a.transpose(1, 0, 2).reshape(-1, a.shape[2])
    raise InputError(f"expected a 2-D or 3-D array, got shape {a.shape}")
