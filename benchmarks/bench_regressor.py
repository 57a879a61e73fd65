"""Regressor throughput: drivegain's batch regressor against a per-sample Pinocchio loop.

Run: ``python benchmarks/bench_regressor.py [--samples N] [--repeats R] [--robot FILE]``.

Both sides produce the same (N, n, 86) standard regressor of the TX-40 (checked first):

- baseline: a Python loop calling ``pin.computeJointTorqueRegressor`` per sample into a
  preallocated (N, n, 10n) array, then, vectorised outside the loop, the reorder of each link's
  ten columns into our order and the rotor-inertia, friction, offset and coupled-motor columns.
  Two ways of reordering are timed (``np.take`` then a block copy; a product with a 0/1
  placement matrix) and the ratio uses the faster one;
- ours: ``drivegain.dynamics.regressor.standard_regressor`` on all samples at once.

Timings are the best of ``--repeats`` interleaved runs, in this thread's CPU time (the ratio uses
it: the machine may be shared) and in wall-clock time; the spread of the per-repeat ratios is
printed too. Also shown, for where the time goes: the Pinocchio calls alone (result discarded),
the cost of allocating and touching a C-ordered output of that size, and ours without its output
memory (the traced operations on one reused output block: private internals). Ours returns a
view of a sample-last array (see ``standard_regressor``); the baseline builds a C-ordered one.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pinocchio as pin

from drivegain.config import load_robot, resource_path
from drivegain.config.robot import WristFriction
from drivegain.dynamics import regressor
from drivegain.dynamics.model import RobotModel, build_model
from drivegain.dynamics.params import FROM_PINOCCHIO, N_PER_JOINT, n_standard


def _pinocchio_rows(
    model: RobotModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray
) -> np.ndarray:
    """Pinocchio's (N, n, 10n) joint torque regressor, one call per sample."""
    pm, n = model.pin_model, model.n
    data = pm.createData()
    raw = np.empty((len(q), n, 10 * n))
    regress = pin.computeJointTorqueRegressor
    for k in range(len(q)):
        raw[k] = regress(pm, data, q[k], qd[k], qdd[k])
    return raw


def _drive_columns(model: RobotModel, out: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> None:
    robot, n = model.robot, model.n
    j = np.arange(n)
    out[:, j, N_PER_JOINT * j + 10] = qdd
    out[:, j, N_PER_JOINT * j + 11] = qd
    out[:, j, N_PER_JOINT * j + 12] = np.sign(qd)
    out[:, j, N_PER_JOINT * j + 13] = 1.0
    physical = WristFriction(robot.wrist_friction) is WristFriction.PHYSICAL
    for k, c in enumerate(robot.couplings):
        m, o = c.motor, c.joint
        ia, col = N_PER_JOINT * m + 10, N_PER_JOINT * n + 2 * k
        out[:, o, ia] = qdd[:, m]
        out[:, m, ia] += qdd[:, o]
        out[:, o, col] = qd[:, m]
        out[:, m, col] = qd[:, o]
        s_sum = np.sign(qd[:, o] + qd[:, m])
        out[:, o, col + 1] = s_sum if physical else np.sign(qd[:, m])
        out[:, m, col + 1] = s_sum if physical else s_sum - np.sign(qd[:, m])


def loop_take(model: RobotModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    """Baseline, reorder by ``np.take`` and a block copy."""
    n, samples = model.n, len(q)
    raw = _pinocchio_rows(model, q, qd, qdd)
    perm = (10 * np.arange(n)[:, None] + FROM_PINOCCHIO[None, :]).ravel()
    ordered = np.take(raw, perm, axis=2)
    out = np.zeros((samples, n, n_standard(model.robot)))
    out[:, :, : N_PER_JOINT * n].reshape(samples, n, n, N_PER_JOINT)[..., :10] = ordered.reshape(
        samples, n, n, 10
    )
    _drive_columns(model, out, qd, qdd)
    return out


def loop_matmul(model: RobotModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    """Baseline, reorder by a product with a 0/1 placement matrix (BLAS)."""
    n, samples, p = model.n, len(q), n_standard(model.robot)
    raw = _pinocchio_rows(model, q, qd, qdd)
    place = np.zeros((10 * n, p))
    for j in range(n):
        place[10 * j + FROM_PINOCCHIO, N_PER_JOINT * j + np.arange(10)] = 1.0
    out = np.empty((samples, n, p))
    np.matmul(raw.reshape(-1, 10 * n), place, out=out.reshape(-1, p))
    _drive_columns(model, out, qd, qdd)
    return out


def bare_pinocchio(model: RobotModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> None:
    pm = model.pin_model
    data = pm.createData()
    regress = pin.computeJointTorqueRegressor
    for k in range(len(q)):
        regress(pm, data, q[k], qd[k], qdd[k])


def ours(model: RobotModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    return regressor.standard_regressor(model, q, qd, qdd)


def output_floor(model: RobotModel, samples: int) -> None:
    """Allocate a zeroed output and write one value per sample (every page touched)."""
    out = np.zeros((samples, model.n, n_standard(model.robot)))
    out[:, 0, 0] = 1.0


def timed(fn: Callable[[], object]) -> tuple[float, float]:
    """(thread CPU, wall) seconds of one call."""
    w0, c0 = time.perf_counter(), time.thread_time()
    fn()
    return time.thread_time() - c0, time.perf_counter() - w0


def breakdown(model: RobotModel, samples: int, repeats: int) -> dict[str, float]:
    """CPU seconds per sample of ours: the traced operations alone, on one reused output block."""
    kern = regressor._kernel(model, WristFriction(model.robot.wrist_friction), "standard", samples)
    chunks = max(1, samples // kern.chunk)
    block = np.zeros((kern.p * model.n, kern.chunk))
    ops, sites = kern.bind(kern.chunk)
    for args, pos, e in sites:
        args[pos] = block[e]

    def arithmetic() -> None:
        for _ in range(chunks):
            for f, op_args in ops:
                f(*op_args)

    res = {"arithmetic": min(timed(arithmetic)[0] for _ in range(repeats)) / (chunks * kern.chunk)}
    for args, pos, _ in sites:
        args[pos] = None
    res["operations per chunk"] = len(ops)
    res["chunk"] = kern.chunk
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--samples", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--robot", type=Path, default=resource_path("tx40.toml"))
    args = ap.parse_args()

    model = build_model(load_robot(args.robot))
    robot = model.robot
    rng = np.random.default_rng(0)
    n, samples = robot.n, args.samples
    q = rng.uniform(-np.pi, np.pi, (samples, n))
    qd = rng.uniform(-1.0, 1.0, (samples, n)) * robot.velocity_limits
    qdd = rng.uniform(-1.0, 1.0, (samples, n)) * robot.acceleration_limits

    # Warm up (ours traces and compiles the model once) and check all give the same matrix.
    mine = ours(model, q, qd, qdd)
    diffs = [np.abs(mine - f(model, q, qd, qdd)).max() for f in (loop_take, loop_matmul)]
    print(f"robot {robot.name}: {samples} samples, output shape {mine.shape}")
    print(f"max |ours - pinocchio loop| = {max(diffs):.2e}")
    del mine

    cases: dict[str, Callable[[], object]] = {
        "pinocchio loop + take": lambda: loop_take(model, q, qd, qdd),
        "pinocchio loop + matmul": lambda: loop_matmul(model, q, qd, qdd),
        "ours (standard_regressor)": lambda: ours(model, q, qd, qdd),
        "  pinocchio calls only": lambda: bare_pinocchio(model, q, qd, qdd),
        "  allocate+touch output": lambda: output_floor(model, samples),
    }
    best = {name: (np.inf, np.inf) for name in cases}
    ratios = []
    for _ in range(args.repeats):
        this: dict[str, float] = {}
        for name, fn in cases.items():
            cpu, wall = timed(fn)
            this[name] = cpu
            best[name] = (min(best[name][0], cpu), min(best[name][1], wall))
        ratios.append(
            min(this["pinocchio loop + take"], this["pinocchio loop + matmul"])
            / this["ours (standard_regressor)"]
        )
    print(f"{'':28}{'samples/s (CPU)':>17}{'us/sample CPU':>15}{'us/sample wall':>16}")
    for name, (cpu, wall) in best.items():
        print(
            f"{name:28}{samples / cpu:>17,.0f}{cpu / samples * 1e6:>15.3f}"
            f"{wall / samples * 1e6:>16.3f}"
        )
    base = min(best["pinocchio loop + take"], best["pinocchio loop + matmul"])
    mine_t = best["ours (standard_regressor)"]
    print(
        f"ratio ours / fastest pinocchio loop: {base[0] / mine_t[0]:.2f}x CPU "
        f"({base[1] / mine_t[1]:.2f}x wall); target >= 5x"
    )
    print(
        f"  per repeat (CPU): min {min(ratios):.2f}x, median {float(np.median(ratios)):.2f}x, "
        f"max {max(ratios):.2f}x over {len(ratios)}"
    )
    parts = breakdown(model, samples, args.repeats)
    print(
        f"ours, where the time goes ({parts['operations per chunk']:.0f} numpy operations per "
        f"chunk of {parts['chunk']:.0f} samples):"
    )
    print(f"  {'operations, output reused':30}{parts['arithmetic'] * 1e6:>8.3f} us/sample CPU")
    print("  the rest: fresh output pages (zeroed by the OS on first write), inputs, sin/cos")


if __name__ == "__main__":
    main()
