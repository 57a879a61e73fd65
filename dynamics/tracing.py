"""Symbolic tracing of the IDIM regressor: the Newton-Euler recursion run once per model on
scalar symbols, giving a flat program of elementwise operations (see :mod:`.regressor`, which
executes it over chunks of samples, for why).

The trace folds every constant of the kinematics (MDH rotations by ±π/2 become signed
permutations, zero offsets vanish, constant gravity in the first frames stays a number), keeps
signs and constant factors symbolic, and shares common products.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from drivegain.config.robot import WristFriction
from drivegain.dynamics.model import RobotModel
from drivegain.dynamics.params import N_INERTIAL, N_PER_JOINT

#: Constants of the kinematics closer than this to 0 or ±1 are taken as exact (cos(π/2) = 6e-17).
_SNAP = 1e-14


# --------------------------------------------------------------------------- symbolic scalars


class Sym(NamedTuple):
    """A traced scalar field: ``coef * slot``, or the constant ``coef`` when ``slot < 0``."""

    coef: float
    slot: int


ZERO = Sym(0.0, -1)
Vec = tuple[Sym, Sym, Sym]


def _snap(x: float) -> float:
    for exact in (0.0, 1.0, -1.0):
        if abs(x - exact) < _SNAP:
            return exact
    return float(x)


def _const(x: float) -> Sym:
    x = _snap(x)
    return ZERO if x == 0.0 else Sym(x, -1)


# Operation kinds. Binary on two slots: mul add sub. Slot and number: muls adds. Unary: sign.
# The final copies into the output rows: copy neg.
UFUNC: dict[str, Callable[..., Any]] = {
    "mul": np.multiply,
    "muls": np.multiply,
    "add": np.add,
    "adds": np.add,
    "sub": np.subtract,
    "sign": np.sign,
    "copy": np.positive,
    "neg": np.negative,
}
UNARY = frozenset({"sign", "copy", "neg"})
Op = tuple[str, int, "int | float | None"]


class Tracer:
    """Records elementwise operations on slots; slot k < n_inputs is an input."""

    def __init__(self, n_inputs: int) -> None:
        self.n_inputs = n_inputs
        self.ops: list[Op] = []
        self._memo: dict[Op, int] = {}

    def emit(self, kind: str, a: int, b: int | float | None = None) -> int:
        key = (kind, a, b)
        slot = self._memo.get(key)
        if slot is None:
            slot = self.n_inputs + len(self.ops)
            self.ops.append(key)
            self._memo[key] = slot
        return slot

    def mul(self, x: Sym, y: Sym) -> Sym:
        if x.coef == 0.0 or y.coef == 0.0:
            return ZERO
        if x.slot < 0:
            return Sym(x.coef * y.coef, y.slot)
        if y.slot < 0:
            return Sym(x.coef * y.coef, x.slot)
        a, b = sorted((x.slot, y.slot))
        return Sym(x.coef * y.coef, self.emit("mul", a, b))

    def add(self, x: Sym, y: Sym) -> Sym:
        if x.coef == 0.0:
            return y
        if y.coef == 0.0:
            return x
        if x.slot < 0 and y.slot < 0:
            return _const(x.coef + y.coef)
        if x.slot < 0:
            x, y = y, x
        if y.slot < 0:
            return Sym(x.coef, self.emit("adds", x.slot, y.coef / x.coef))
        if x.slot == y.slot:
            c = x.coef + y.coef
            return ZERO if c == 0.0 else Sym(c, x.slot)
        if x.coef < 0.0 < y.coef and x.coef == -y.coef:
            x, y = y, x  # y - x rather than -(x - y): saves a negation if this is an output
        ratio = y.coef / x.coef
        if ratio == 1.0:
            a, b = sorted((x.slot, y.slot))
            return Sym(x.coef, self.emit("add", a, b))
        if ratio == -1.0:
            return Sym(x.coef, self.emit("sub", x.slot, y.slot))
        if abs(ratio) > 1.0:  # scale the smaller term: keeps the result's coefficient small
            x, y, ratio = y, x, 1.0 / ratio
        scaled = self.emit("muls", y.slot, ratio)
        a, b = sorted((x.slot, scaled))
        return Sym(x.coef, self.emit("add", a, b))

    def unit(self, x: Sym) -> Sym:
        """``x`` with its constant factor applied, keeping only a sign lazy.

        Sums of terms with different factors need a scaling each; applying a factor that is used
        in many sums once is cheaper (gravity's 9.81 would otherwise ride along everywhere).
        """
        if x.slot < 0 or abs(x.coef) == 1.0:
            return x
        return Sym(float(np.sign(x.coef)), self.emit("muls", x.slot, abs(x.coef)))

    def vunit(self, v: Vec) -> Vec:
        return (self.unit(v[0]), self.unit(v[1]), self.unit(v[2]))

    def neg(self, x: Sym) -> Sym:
        return Sym(-x.coef, x.slot) if x.coef != 0.0 else ZERO

    def sub(self, x: Sym, y: Sym) -> Sym:
        return self.add(x, self.neg(y))

    def sign(self, x: Sym) -> Sym:
        if x.slot < 0:
            return _const(float(np.sign(x.coef)))
        return Sym(float(np.sign(x.coef)), self.emit("sign", x.slot))

    def total(self, terms: Sequence[Sym]) -> Sym:
        # Start from a positive term: the sum then carries a positive factor.
        acc = ZERO
        for t in sorted(terms, key=lambda s: s.coef <= 0.0):
            acc = self.add(acc, t)
        return acc

    def dot(self, a: Sequence[Sym], b: Sequence[Sym]) -> Sym:
        return self.total([self.mul(x, y) for x, y in zip(a, b, strict=True)])

    # 3-vectors and 3x3 matrices of symbols ------------------------------------------------
    def vadd(self, a: Vec, b: Vec) -> Vec:
        return (self.add(a[0], b[0]), self.add(a[1], b[1]), self.add(a[2], b[2]))

    def vscale(self, v: Vec, s: Sym) -> Vec:
        return (self.mul(v[0], s), self.mul(v[1], s), self.mul(v[2], s))

    def cross(self, a: Vec, b: Vec) -> Vec:
        return (
            self.sub(self.mul(a[1], b[2]), self.mul(a[2], b[1])),
            self.sub(self.mul(a[2], b[0]), self.mul(a[0], b[2])),
            self.sub(self.mul(a[0], b[1]), self.mul(a[1], b[0])),
        )

    def mat_t_vec(self, m: Sequence[Sequence[Sym]], v: Vec) -> Vec:
        """``m.T @ v``."""
        return (
            self.dot([m[0][0], m[1][0], m[2][0]], v),
            self.dot([m[0][1], m[1][1], m[2][1]], v),
            self.dot([m[0][2], m[1][2], m[2][2]], v),
        )

    def matmul(self, a: Sequence[Sequence[Sym]], b: Sequence[Sequence[Sym]]) -> list[list[Sym]]:
        cols = len(b[0])
        return [[self.dot(row, [b[k][c] for k in range(len(b))]) for c in range(cols)] for row in a]


def _const_vec(v: np.ndarray) -> Vec:
    return (_const(v[0]), _const(v[1]), _const(v[2]))


def _const_mat(m: np.ndarray) -> list[list[Sym]]:
    return [[_const(m[r, c]) for c in range(3)] for r in range(3)]


def _skew(t: Tracer, v: Vec) -> list[list[Sym]]:
    z = ZERO
    return [[z, t.neg(v[2]), v[1]], [v[2], z, t.neg(v[0])], [t.neg(v[1]), v[0], z]]


def _axis_rotation(t: Tracer, axis: np.ndarray, c: Sym, s: Sym) -> list[list[Sym]]:
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


def _link_wrench(t: Tracer, w: Vec, wd: Vec, acc: Vec) -> tuple[list[list[Sym]], list[list[Sym]]]:
    """Wrench of a link about its frame origin per inertial parameter, in the link frame.

    Returns ``(kn, kf)``, each 3 rows of 10 symbols: moment and force per
    ``[XX XY XZ YY YZ ZZ MX MY MZ M]``. With ``c`` the first moment and ``I`` the inertia at the
    origin: ``n = I ẇ + w × I w + c × a`` and ``f = M a + ẇ × c + w × (w × c)``.
    """

    def inertia_map(v: Vec) -> list[list[Sym]]:  # I v = L(v) [XX XY XZ YY YZ ZZ]
        z = ZERO
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
    kn = [k_inertia[r] + k_moment_c[r] + [ZERO] for r in range(3)]
    kf = [[ZERO] * 6 + k_force_c[r] + [acc[r]] for r in range(3)]
    return kn, kf


@dataclass(frozen=True)
class Program:
    """A traced regressor: operations, and the symbol of every entry."""

    n: int
    ops: list[Op]
    rigid: dict[tuple[int, int, int], Sym]  # (joint row, link, inertial parameter)
    extra: dict[tuple[int, int], Sym]  # (joint row, standard column) beyond the inertial ones


def trace_program(model: RobotModel, form: WristFriction) -> Program:
    n = model.n
    # Input slots: sin q, cos q, qd, qdd (n each), filled per chunk.
    sin0, cos0, qd0, qdd0 = 0, n, 2 * n, 3 * n
    t = Tracer(4 * n)
    zero3: Vec = (ZERO, ZERO, ZERO)
    qd_ = [Sym(1.0, qd0 + j) for j in range(n)]
    qdd_ = [Sym(1.0, qdd0 + j) for j in range(n)]
    rigid: dict[tuple[int, int, int], Sym] = {}
    # Base frame at rest; gravity enters as an upward acceleration of the base.
    w, wd, acc = zero3, zero3, _const_vec(-np.asarray(model.gravity, dtype=float))
    screws: list[tuple[Vec, Vec]] = []  # unit screws (axis, moment at origin) of joints < j
    for j in range(n):
        fixed = _const_mat(model.rotations[j])
        p = _const_vec(model.translations[j])
        u = _const_vec(model.axes[j])
        rq = _axis_rotation(t, model.axes[j], Sym(1.0, cos0 + j), Sym(1.0, sin0 + j))

        def to_child(v: Vec, rq: list[list[Sym]] = rq, f: list[list[Sym]] = fixed) -> Vec:
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

    extra: dict[tuple[int, int], Sym] = {}
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
    return Program(n=n, ops=t.ops, rigid=rigid, extra=extra)
