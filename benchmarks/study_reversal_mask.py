"""What the reversal mask (``identify --reversal-mask S``) does to our gains and payloads in
closed loop (issue 17 study).

The closed-loop scenarios of the validation study, ours (the maximum-likelihood gains, then
Case 2's payloads as the study fits them), each seed prepared without the mask and with each
taper asked: the same simulated runs every way. Printed per scenario and taper: RMS gain error
per joint (% of the gain), median σ̂, standard deviation and mean of z = (ĝ − g)/σ̂ over the
seeds, pooled ±2σ coverage of the gains; for runs b and c's payloads, the range over their 19
parameters of the standard deviation and mean of z and the pooled coverage; then the ratio of
each taper's RMS gain error to the plain one's, measured in the same run. ``auto`` among the
tapers prepares the runs as ``identify --reversal-mask auto`` does: the mask (0.05 s) only on
the drives whose fit's κ̂ says they stick.

``--periods K`` repeats the shipped excitation K times as long (the study's runs are 30 s, 231
decimated samples): how the σ̂ of masked runs depends on the length of the recording
(docs/model.md, "Weighting the reversals out before the decimation"). The random excitations
keep their own length, so it applies to the shipped excitation's scenarios only.

Usage: python benchmarks/study_reversal_mask.py [--seeds 24] [--tapers 0.05,0.1]
       [--scenarios closed-loop,random-closed-loop] [--periods 1] [--workers 2]
"""

from __future__ import annotations

import argparse
import functools
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

#: the --tapers entry for the gate of ``identify --reversal-mask auto`` (identify.maskgate)
AUTO = "auto"


@dataclass(frozen=True)
class SeedOutcome:
    """One seed of one scenario at one taper (None: no mask)."""

    scenario: str
    taper: float | str | None  # str: "auto"
    seed: int
    gain_z: np.ndarray  # (n,)
    gain_err: np.ndarray  # relative, (n,)
    gain_std: np.ndarray  # relative, (n,)
    payload_z: np.ndarray  # (19,): run b's 10 then run c's 9 unknown (its mass is known)


@functools.cache
def _world(periods: int = 1):
    from drivegain.validation.world import make_world, with_trajectory

    world = make_world()
    if periods == 1:
        return world
    return with_trajectory(world, replace(world.fourier, periods=world.fourier.periods * periods))


def _payload_z(res, world) -> np.ndarray:
    from drivegain.validation.estimators import OURS
    from drivegain.validation.statistics import payload_z

    # pooled as the study pools them (statistics.payload_z_stats): run b's known mass left
    # out (the gains reproduce it), and what Case 2 did not estimate (NaN: run c's known mass)
    zb = payload_z([res], OURS, world.payload.values, "b")[0]
    zb[world.payload.known_mask()] = np.nan
    z = np.concatenate([zb, payload_z([res], OURS, world.validation.values, "c")[0]])
    return z[np.isfinite(z)]


def _one(task: tuple[str, float | str | None, int, int]) -> SeedOutcome:
    from drivegain.identify.blas import limited_blas_threads
    from drivegain.validation.estimators import METHODS, OURS, run_seed
    from drivegain.validation.scenarios import SCENARIOS

    key, taper, seed, periods = task
    sc = next(s for s in SCENARIOS if s.key == key)
    world = _world(periods)
    if taper == AUTO:  # as identify --reversal-mask auto (run_designs)
        world = replace(world, mask_auto=True)
    elif taper is not None:  # seed_world keeps it when it draws a random trajectory
        world = replace(world, settings=replace(world.settings, reversal_mask_s=float(taper)))
    truth = np.asarray(world.truth.gains, dtype=float)
    with limited_blas_threads(1):
        res = run_seed(world, seed, sc, [m for m in METHODS if m.key == OURS])
    if OURS not in res.gains:
        raise RuntimeError(f"{key} seed {seed} taper {taper}: {res.failures}")
    g, s = res.gains[OURS], res.std[OURS]
    return SeedOutcome(
        key,
        taper,
        seed,
        (g - truth) / s,
        (g - truth) / np.abs(truth),
        s / np.abs(truth),
        _payload_z(res, world),
    )


def _level(t: float | str) -> str:
    return "auto (gated)" if t == AUTO else f"taper {float(t):g} s"


def _row(name: str, values: np.ndarray, digits: int = 3) -> str:
    return f"{name:30s}" + "".join(f"{v:9.{digits}f}" for v in values)


def study(
    scenarios: list[str],
    tapers: list[float | str],
    seeds: int,
    workers: int,
    periods: int = 1,
) -> list[SeedOutcome]:
    """Run the study and print its tables (see the module docstring).

    Raises
    ------
    ValueError
        Fewer than 2 seeds, an unknown scenario, a taper outside (0, 1] s, fewer than one
        period, or more than one with a random excitation's scenario.
    """
    from drivegain.validation.scenarios import SCENARIOS, Excitation

    by_key = {s.key: s for s in SCENARIOS}
    if seeds < 2:
        raise ValueError(f"need 2 seeds or more, got {seeds}")
    if bad := [s for s in scenarios if s not in by_key]:
        raise ValueError(f"unknown scenario {bad[0]!r} (known: {', '.join(sorted(by_key))})")
    if bad_t := [t for t in tapers if t != AUTO and not 0.0 < float(t) <= 1.0]:
        raise ValueError(f"a taper is in (0, 1] s, got {bad_t[0]}")
    if periods < 1:
        raise ValueError(f"--periods needs 1 or more, got {periods}")
    if periods > 1 and (
        rand := [s for s in scenarios if by_key[s].excitation is Excitation.RANDOM]
    ):
        raise ValueError(f"--periods lengthens the shipped excitation only, not {rand[0]!r}'s")
    levels: list[float | str | None] = [None, *tapers]
    tasks = [(k, t, s, periods) for k in scenarios for s in range(seeds) for t in levels]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(workers) as pool:
        out = list(pool.map(_one, tasks))
    for key in scenarios:
        rms = {}
        longer = f", the excitation {periods}x as long" if periods > 1 else ""
        print(f"\n{key}: {seeds} seeds, ours{longer}")
        for t in levels:
            rows = [o for o in out if o.scenario == key and o.taper == t]
            z = np.array([o.gain_z for o in rows])
            err = 100 * np.array([o.gain_err for o in rows])
            pz = np.array([o.payload_z for o in rows])
            rms[t] = np.sqrt(np.mean(err**2, axis=0))
            name = "no mask" if t is None else _level(t)
            print(f"  {name}" + "".join(f"{'j' + str(j + 1):>9s}" for j in range(z.shape[1])))
            print(_row("    RMS gain error, %", rms[t]))
            print(_row("    median σ̂, %", np.median(100 * np.array([o.gain_std for o in rows]), 0)))
            print(_row("    std of z", z.std(axis=0, ddof=1), 2))
            print(_row("    mean of z", z.mean(axis=0), 2))
            psd, pmean = pz.std(axis=0, ddof=1), pz.mean(axis=0)
            print(
                f"    gains within ±2σ {np.mean(np.abs(z) <= 2):.1%}; payloads: std of z "
                f"{psd.min():.2f}-{psd.max():.2f}, mean of z {pmean.min():+.2f} to "
                f"{pmean.max():+.2f}, within ±2σ {np.mean(np.abs(pz) <= 2):.1%}"
            )
        for t in tapers:
            print(_row(f"  ratio {_level(t)} / no mask", rms[t] / rms[None], 2))
    print(f"\n{len(tasks)} seed runs of three recordings in {time.perf_counter() - t0:.0f} s")
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--seeds", type=int, default=24, help="noise seeds per scenario (24)")
    p.add_argument(
        "--tapers",
        default="0.05,0.1",
        help="tapers to compare, s, or auto: the gate of --reversal-mask auto (0.05,0.1)",
    )
    p.add_argument("--scenarios", default="closed-loop,random-closed-loop")
    p.add_argument("--periods", type=int, default=1, help="shipped excitation K times as long (1)")
    p.add_argument("--workers", type=int, default=2, help="processes (2)")
    a = p.parse_args()
    try:
        tapers = [x if x == AUTO else float(x) for x in a.tapers.split(",")]
    except ValueError:
        p.error(f"--tapers: numbers separated by commas, got {a.tapers!r}")
    if a.workers < 1:
        p.error("--workers needs 1 or more")
    try:
        study(a.scenarios.split(","), tapers, a.seeds, a.workers, a.periods)
    except ValueError as exc:
        p.error(str(exc))


if __name__ == "__main__":
    main()
