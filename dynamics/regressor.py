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
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

import numpy as np

from drivegain.config.robot import WristFriction
from drivegain.dynamics.model import RobotModel
from drivegain.dynamics.params import N_INERTIAL, N_PER_JOINT, n_standard

#: Samples per pass of the traced program: amortises numpy's per-call overhead (about 0.4 µs
#: for each of the ~930 operations of the TX-40) while the ~70 work rows stay near L2 size.
#: Measured for 20 000 samples (best/median of 9, µs per sample): 2048 → 1.24/1.34,
#: 4096 → 0.92-0.98/1.05, 8192 → 1.05-1.11/1.13-1.15, 16384 → 1.01-1.08/1.08-1.11.
CHUNK = 4096
_MIN_CHUNK = 16
#: Constants of the kinematics closer than this to 0 or ±1 are taken as exact (cos(π/2) = 6e-17).
_SNAP = 1e-14


# --------------------------------------------------------------------------- symbolic scalars


class _Sym(NamedTuple):
    """A traced scalar field: ``coef * slot``, or the constant ``coef`` when ``slot < 0``."""

    coef: float
    slot: int


_ZERO = _Sym(0.0, -1)
_Vec = tuple[_Sym, _Sym, _Sym]


def _snap(x: float) -> float:
    for exact in (0.0, 1.0, -1.0):
        if abs(x - exact) < _SNAP:
            return exact
    return float(x)


def _const(x: float) -> _Sym:
    x = _snap(x)
    return _ZERO if x == 0.0 else _Sym(x, -1)


# Operation kinds. Binary on two slots: mul add sub. Slot and number: muls adds. Unary: sign.
# The final copies into the output rows: copy neg.
_UFUNC: dict[str, Callable[..., Any]] = {
    "mul": np.multiply,
    "muls": np.multiply,
    "add": np.add,
    "adds": np.add,
    "sub": np.subtract,
    "sign": np.sign,
    "copy": np.positive,
    "neg": np.negative,
}
_UNARY = frozenset({"sign", "copy", "neg"})
_Op = tuple[str, int, "int | float | None"]


class _Tracer:
    """Records elementwise operations on slots; slot k < n_inputs is an input."""

    def __init__(self, n_inputs: int) -> None:
        self.n_inputs = n_inputs
        self.ops: list[_Op] = []
        self._memo: dict[_Op, int] = {}

    def emit(self, kind: str, a: int, b: int | float | None = None) -> int:
        key = (kind, a, b)
        slot = self._memo.get(key)
        if slot is None:
            slot = self.n_inputs + len(self.ops)
            self.ops.append(key)
            self._memo[key] = slot
        return slot

    def mul(self, x: _Sym, y: _Sym) -> _Sym:
        if x.coef == 0.0 or y.coef == 0.0:
            return _ZERO
        if x.slot < 0:
            return _Sym(x.coef * y.coef, y.slot)
        if y.slot < 0:
            return _Sym(x.coef * y.coef, x.slot)
        a, b = sorted((x.slot, y.slot))
        return _Sym(x.coef * y.coef, self.emit("mul", a, b))

    def add(self, x: _Sym, y: _Sym) -> _Sym:
        if x.coef == 0.0:
            return y
        if y.coef == 0.0:
            return x
        if x.slot < 0 and y.slot < 0:
            return _const(x.coef + y.coef)
        if x.slot < 0:
            x, y = y, x
        if y.slot < 0:
            return _Sym(x.coef, self.emit("adds", x.slot, y.coef / x.coef))
        if x.slot == y.slot:
            c = x.coef + y.coef
            return _ZERO if c == 0.0 else _Sym(c, x.slot)
        if x.coef < 0.0 < y.coef and x.coef == -y.coef:
            x, y = y, x  # y - x rather than -(x - y): saves a negation if this is an output
        ratio = y.coef / x.coef
        if ratio == 1.0:
            a, b = sorted((x.slot, y.slot))
            return _Sym(x.coef, self.emit("add", a, b))
        if ratio == -1.0:
            return _Sym(x.coef, self.emit("sub", x.slot, y.slot))
        if abs(ratio) > 1.0:  # scale the smaller term: keeps the result's coefficient small
            x, y, ratio = y, x, 1.0 / ratio
        scaled = self.emit("muls", y.slot, ratio)
        a, b = sorted((x.slot, scaled))
        return _Sym(x.coef, self.emit("add", a, b))

    def unit(self, x: _Sym) -> _Sym:
        """``x`` with its constant factor applied, keeping only a sign lazy.

        Sums of terms with different factors need a scaling each; applying a factor that is used
        in many sums once is cheaper (gravity's 9.81 would otherwise ride along everywhere).
        """
        if x.slot < 0 or abs(x.coef) == 1.0:
            return x
        return _Sym(float(np.sign(x.coef)), self.emit("muls", x.slot, abs(x.coef)))

    def vunit(self, v: _Vec) -> _Vec:
        return (self.unit(v[0]), self.unit(v[1]), self.unit(v[2]))

    def neg(self, x: _Sym) -> _Sym:
        return _Sym(-x.coef, x.slot) if x.coef != 0.0 else _ZERO

    def sub(self, x: _Sym, y: _Sym) -> _Sym:
        return self.add(x, self.neg(y))

    def sign(self, x: _Sym) -> _Sym:
        if x.slot < 0:
            return _const(float(np.sign(x.coef)))
        return _Sym(float(np.sign(x.coef)), self.emit("sign", x.slot))

    def total(self, terms: Sequence[_Sym]) -> _Sym:
        # Start from a positive term: the sum then carries a positive factor.
        acc = _ZERO
        for t in sorted(terms, key=lambda s: s.coef <= 0.0):
            acc = self.add(acc, t)
        return acc

    def dot(self, a: Sequence[_Sym], b: Sequence[_Sym]) -> _Sym:
        return self.total([self.mul(x, y) for x, y in zip(a, b, strict=True)])

    # 3-vectors and 3x3 matrices of symbols ------------------------------------------------
    def vadd(self, a: _Vec, b: _Vec) -> _Vec:
        return (self.add(a[0], b[0]), self.add(a[1], b[1]), self.add(a[2], b[2]))

    def vscale(self, v: _Vec, s: _Sym) -> _Vec:
        return (self.mul(v[0], s), self.mul(v[1], s), self.mul(v[2], s))

    def cross(self, a: _Vec, b: _Vec) -> _Vec:
        return (
            self.sub(self.mul(a[1], b[2]), self.mul(a[2], b[1])),
            self.sub(self.mul(a[2], b[0]), self.mul(a[0], b[2])),
            self.sub(self.mul(a[0], b[1]), self.mul(a[1], b[0])),
        )

    def mat_t_vec(self, m: Sequence[Sequence[_Sym]], v: _Vec) -> _Vec:
        """``m.T @ v``."""
        return (
            self.dot([m[0][0], m[1][0], m[2][0]], v),
            self.dot([m[0][1], m[1][1], m[2][1]], v),
            self.dot([m[0][2], m[1][2], m[2][2]], v),
        )

    def matmul(self, a: Sequence[Sequence[_Sym]], b: Sequence[Sequence[_Sym]]) -> list[list[_Sym]]:
        cols = len(b[0])
        return [[self.dot(row, [b[k][c] for k in range(len(b))]) for c in range(cols)] for row in a]


def _const_vec(v: np.ndarray) -> _Vec:
    return (_const(v[0]), _const(v[1]), _const(v[2]))


def _const_mat(m: np.ndarray) -> list[list[_Sym]]:
    return [[_const(m[r, c]) for c in range(3)] for r in range(3)]


def _skew(t: _Tracer, v: _Vec) -> list[list[_Sym]]:
    z = _ZERO
    return [[z, t.neg(v[2]), v[1]], [v[2], z, t.neg(v[0])], [t.neg(v[1]), v[0], z]]


def _axis_rotation(t: _Tracer, axis: np.ndarray, c: _Sym, s: _Sym) -> list[list[_Sym]]:
    """Rotation by angle q about a constant unit axis u: u uᵀ + cos q (I - u uᵀ) + sin q [u]×."""
    u = np.array([_snap(x) for x in axis])
    uu = np.outer(u, u)
    k = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    eye = np.eye(3)
    return [
        [
            t.add(
                t.add(_const(uu[a, b]), t.mul(_const(eye[a, b] - uu[a, b]), c)),
                t.mul(_const(k[a, b]), s),
            )
            for b in range(3)
        ]
        for a in range(3)
    ]


def _link_wrench(
    t: _Tracer, w: _Vec, wd: _Vec, acc: _Vec
) -> tuple[list[list[_Sym]], list[list[_Sym]]]:
    """Wrench of a link about its frame origin per inertial parameter, in the link frame.

    Returns ``(kn, kf)``, each 3 rows of 10 symbols: moment and force per
    ``[XX XY XZ YY YZ ZZ MX MY MZ M]``. With ``c`` the first moment and ``I`` the inertia at the
    origin: ``n = I ẇ + w × I w + c × a`` and ``f = M a + ẇ × c + w × (w × c)``.
    """

    def inertia_map(v: _Vec) -> list[list[_Sym]]:  # I v = L(v) [XX XY XZ YY YZ ZZ]
        z = _ZERO
        return [
            [v[0], v[1], v[2], z, z, z],
            [z, v[0], z, v[1], v[2], z],
            [z, z, v[0], z, v[1], v[2]],
        ]

    sw = _skew(t, w)
    k_inertia = [
        [t.add(x, y) for x, y in zip(r1, r2, strict=True)]
        for r1, r2 in zip(inertia_map(wd), t.matmul(sw, inertia_map(w)), strict=True)
    ]
    k_moment_c = [[t.neg(x) for x in row] for row in _skew(t, acc)]
    k_force_c = [
        [t.add(x, y) for x, y in zip(r1, r2, strict=True)]
        for r1, r2 in zip(_skew(t, wd), t.matmul(sw, sw), strict=True)
    ]
    kn = [k_inertia[r] + k_moment_c[r] + [_ZERO] for r in range(3)]
    kf = [[_ZERO] * 6 + k_force_c[r] + [acc[r]] for r in range(3)]
    return kn, kf


@dataclass(frozen=True)
class _Program:
    """A traced regressor: operations, and the symbol of every entry."""

    n: int
    ops: list[_Op]
    rigid: dict[tuple[int, int, int], _Sym]  # (joint row, link, inertial parameter)
    extra: dict[tuple[int, int], _Sym]  # (joint row, standard column) beyond the inertial ones


def _trace(model: RobotModel, form: WristFriction) -> _Program:
    n = model.n
    # Input slots: sin q, cos q, qd, qdd (n each), filled per chunk.
    sin0, cos0, qd0, qdd0 = 0, n, 2 * n, 3 * n
    t = _Tracer(4 * n)
    zero3: _Vec = (_ZERO, _ZERO, _ZERO)
    qd_ = [_Sym(1.0, qd0 + j) for j in range(n)]
    qdd_ = [_Sym(1.0, qdd0 + j) for j in range(n)]
    rigid: dict[tuple[int, int, int], _Sym] = {}
    # Base frame at rest; gravity enters as an upward acceleration of the base.
    w, wd, acc = zero3, zero3, _const_vec(-np.asarray(model.gravity, dtype=float))
    screws: list[tuple[_Vec, _Vec]] = []  # unit screws (axis, moment at origin) of joints < j
    for j in range(n):
        fixed = _const_mat(model.rotations[j])
        p = _const_vec(model.translations[j])
        u = _const_vec(model.axes[j])
        rq = _axis_rotation(t, model.axes[j], _Sym(1.0, cos0 + j), _Sym(1.0, sin0 + j))

        def to_child(v: _Vec, rq: list[list[_Sym]] = rq, f: list[list[_Sym]] = fixed) -> _Vec:
            # Frame j = parent · F_j · Rot(u_j, q_j): parent coordinates -> frame j.
            return t.mat_t_vec(rq, t.mat_t_vec(f, v))

        acc_origin = t.vadd(acc, t.vadd(t.cross(wd, p), t.cross(w, t.cross(w, p))))
        w_parent = to_child(w)
        u_qd = t.vscale(u, qd_[j])
        w = t.vadd(w_parent, u_qd)
        wd = t.vadd(t.vadd(to_child(wd), t.vscale(u, qdd_[j])), t.cross(w_parent, u_qd))
        w, wd, acc = t.vunit(w), t.vunit(wd), t.vunit(to_child(acc_origin))
        # Screws of the joints before j, moved to frame j: moment at the new origin, rotated.
        screws = [
            (t.vunit(to_child(a)), t.vunit(to_child(t.vadd(b, t.cross(a, p))))) for a, b in screws
        ]
        screws.append((u, zero3))
        kn, kf = _link_wrench(t, w, wd, acc)
        kn = [[t.unit(x) for x in row] for row in kn]
        kf = [[t.unit(x) for x in row] for row in kf]
        for i, (a, b) in enumerate(screws):
            for k in range(N_INERTIAL):
                rigid[(i, j, k)] = t.total(
                    [t.mul(a[r], kn[r][k]) for r in range(3)]
                    + [t.mul(b[r], kf[r][k]) for r in range(3)]
                )

    extra: dict[tuple[int, int], _Sym] = {}
    for j in range(n):
        base = N_PER_JOINT * j
        extra[(j, base + 10)] = qdd_[j]
        extra[(j, base + 11)] = qd_[j]
        extra[(j, base + 12)] = t.sign(qd_[j])
        extra[(j, base + 13)] = _const(1.0)
    for k, c in enumerate(model.robot.couplings):
        m, o = c.motor, c.joint
        ia = N_PER_JOINT * m + 10
        # Motor m turns with q_m + q_o: its rotor inertia couples the two rows.
        extra[(o, ia)] = qdd_[m]
        extra[(m, ia)] = t.add(qdd_[m], qdd_[o])
        col = N_PER_JOINT * n + 2 * k
        extra[(o, col)] = qd_[m]
        extra[(m, col)] = qd_[o]
        s_sum = t.sign(t.add(qd_[o], qd_[m]))
        if form is WristFriction.PHYSICAL:
            extra[(o, col + 1)] = s_sum
            extra[(m, col + 1)] = s_sum
        else:  # the paper's eq. (22) as printed
            s_m = t.sign(qd_[m])
            extra[(o, col + 1)] = s_m
            extra[(m, col + 1)] = t.sub(s_sum, s_m)
    return _Program(n=n, ops=t.ops, rigid=rigid, extra=extra)


_Layout = Literal["standard", "rigid"]


def _entries(model: RobotModel, prog: _Program, layout: _Layout) -> tuple[int, dict[int, _Sym]]:
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


def _sources(op: _Op) -> tuple[int, ...]:
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

    def __init__(self, model: RobotModel, prog: _Program, layout: _Layout, chunk: int) -> None:
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
        after: dict[int, list[tuple[_Op, int]]] = {}  # slot -> final ops reading it
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
                final: _Op = ("copy", sym.slot, None)
            elif sym.coef == -1.0:
                final = ("neg", sym.slot, None)
            else:
                final = ("muls", sym.slot, sym.coef)
            after.setdefault(sym.slot, []).append((final, e))

        # Execution order: finals on inputs first, then each live op followed by its finals.
        seq: list[tuple[_Op, int, int]] = []  # (op, result slot or -1, output row or -1)
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
            if kind not in _BINARY and kind not in _UNARY:
                args.append(("c", float(b)))  # type: ignore[arg-type]
            self.plan.append((_UFUNC[kind], (*args, dst)))
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


def _program(model: RobotModel, form: WristFriction) -> _Program:
    store = _model_cache(model)
    with _CACHE_LOCK:
        prog = store.get(("program", form))
    if prog is None:
        prog = _trace(model, form)
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
        raise ValueError(
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
        raise ValueError(f"{name} must have shape (samples, {n}), got {np.shape(x)}")
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
    raise ValueError(f"expected a 2-D or 3-D array, got shape {a.shape}")
