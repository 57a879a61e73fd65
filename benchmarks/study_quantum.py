"""How much of the gains' missing σ a re-quantisation bootstrap recovers (issue 17 study).

The gains' σ misses the encoder quantum's error (docs/model.md, "What σ does not contain
yet"). This study tries the candidate remedy before it is built into ``identify``: for each
noise seed, the positions are low-passed as the preparation does, quantised again on K random
grids of the same step, prepared and fitted again; the spread of the K gain vectors estimates
the quantum's share of the gains' variance, and their mean minus the estimate its bias (a
SIMEX-style, linear extrapolation: the second quantisation doubles the error).

Printed: per seed, the quantum's σ and bias in units of the reported σ; then over the seeds,
the RMS of z = (ĝ − g)/σ̂, the ±2σ coverage, the mean and spread of z per joint, for three σ:
the HAC σ alone, the HAC σ with the quantum's variance added, and the latter with the
estimated bias removed.

Usage: python benchmarks/study_quantum.py [--seeds 40] [--replicates 8] [--torque-noise 0.05]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_identify import QUANTUM, _sim_world

RATE_HZ = 250.0
SECONDS = 60.0


def study(seeds: int, replicates: int, torque_noise: float) -> None:
    """Run the study and print its table (see the module docstring)."""
    from drivegain.config.robot import WristFriction
    from drivegain.identify.blas import limited_blas_threads
    from drivegain.identify.design import make_design
    from drivegain.identify.gains import estimate_gains
    from drivegain.identify.prepare import prepare_recording
    from drivegain.identify.signal import default_filter, derivatives
    from drivegain.identify.synth import quantise, simulate_run

    with limited_blas_threads(1):
        robot, model, truth, payload, bases, columns, ex = _sim_world(20120701)
        form = WristFriction.PHYSICAL
        t = np.arange(0.0, SECONDS, 1.0 / RATE_HZ)
        settings = default_filter(RATE_HZ, 1.0)

        def prepare(q: np.ndarray, current: np.ndarray, pay):
            return prepare_recording(
                model,
                columns,
                label="loaded" if pay is not None else "unloaded",
                q=q,
                current=current,
                rate_hz=RATE_HZ,
                settings=settings,
                payload=pay,
                period_s=5.0,
            )

        def gains(runs) -> tuple[np.ndarray, np.ndarray]:
            a, b = (make_design(r, bases[form], form, robot) for r in runs)
            res = estimate_gains(a, b, payload, robot.apriori_gains)
            return res.gains, res.std

        z: dict[str, list[np.ndarray]] = {"HAC": [], "HAC + quantum": [], "bias removed": []}
        for seed in range(seeds):
            t0 = time.perf_counter()
            rng = np.random.default_rng(10_000 + seed)
            sims = []
            for which, pay in ((0, None), (1, payload)):
                q, qd, qdd = ex[which].evaluate(t)[:3]
                sim = simulate_run(
                    model,
                    truth,
                    q,
                    qd,
                    qdd,
                    payload=pay,
                    rng=rng,
                    quantum=QUANTUM,
                    torque_noise=torque_noise,
                )
                sims.append((sim, pay))
            g, sd = gains([prepare(s.q, s.current_reference, p) for s, p in sims])
            smooth = [derivatives(s.q, RATE_HZ, settings)[0] for s, _ in sims]
            rr = np.random.default_rng((20120701, seed, 2))
            reps = np.array(
                [
                    gains(
                        [
                            prepare(quantise(qf, QUANTUM, rr), s.current_reference, p)
                            for qf, (s, p) in zip(smooth, sims, strict=True)
                        ]
                    )[0]
                    for _ in range(replicates)
                ]
            )
            var_q = reps.var(axis=0, ddof=1)
            bias = reps.mean(axis=0) - g
            err = g - truth.gains
            z["HAC"].append(err / sd)
            z["HAC + quantum"].append(err / np.sqrt(sd**2 + var_q))
            z["bias removed"].append(
                (err - bias) / np.sqrt(sd**2 + var_q * (1.0 + 1.0 / replicates))
            )
            print(
                f"seed {seed:3d} ({time.perf_counter() - t0:.1f} s): quantum σ/σ "
                f"{np.array2string(np.sqrt(var_q) / sd, precision=2)}, bias/σ "
                f"{np.array2string(bias / sd, precision=2)}",
                flush=True,
            )
        print(
            f"{seeds} seeds, 2 x {SECONDS:g} s at {RATE_HZ:g} Hz, torque noise {torque_noise:g} "
            f"N·m, quantum {np.rad2deg(QUANTUM):g}°, {replicates} re-quantisations per seed"
        )
        for name, values in z.items():
            zz = np.array(values)
            print(
                f"  {name:14s} RMS z {np.sqrt(np.mean(zz**2)):.2f}, ±2σ coverage "
                f"{100.0 * np.mean(np.abs(zz) < 2.0):.1f} %, mean z "
                f"{np.array2string(zz.mean(axis=0), precision=2)}, spread "
                f"{np.array2string(zz.std(axis=0), precision=2)}"
            )


def main() -> None:
    """Command line of the study."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=40)
    parser.add_argument("--replicates", type=int, default=8)
    parser.add_argument("--torque-noise", type=float, default=0.05, help="N·m")
    args = parser.parse_args()
    study(args.seeds, args.replicates, args.torque_noise)


if __name__ == "__main__":
    main()
