"""Time and peak memory of ``drivegain identify`` (issue 3's benchmark).

Cases:
  (a) the real TX-40 recording (45 000 samples at 5 kHz, one unloaded run, gains = gear ratios),
  (b) two simulated 60 s runs at 250 Hz (unloaded + 4.59 kg payload, IDIM-WTLS), target < 10 s,
  (c) two simulated 10-minute runs at 1 kHz,
  and a scaling series of (b)-like runs of 30 to 240 s, to see how time and memory grow.

Each identification runs in a fresh process (peak RSS = its ru_maxrss, or its largest worker's);
the memory column is the peak minus that of a process that only imported the pipeline. Times are
printed as seconds and as ratios to a baseline measured in the same run (a fixed numpy workload),
so runs on different machines compare. Logs are written to a temporary folder first (not timed).

Usage: python benchmarks/bench_identify.py [--quick] [--keep DIR]
       python benchmarks/bench_identify.py --study SEEDS   (coverage and σ studies)
       python benchmarks/bench_identify.py --read [--keep DIR]   (read_run of a 600 s, 1 kHz log
           through its /joint_states/columns blocks beside its JSON messages, same process)
       python benchmarks/bench_identify.py --baseline-ref [REF] [--quick] [--repeats K]
           whole ``drivegain identify`` commands of this tree beside those of REF (default
           c03ea6b, the release before issue 19), installed in a temporary venv by the
           benchmark (benchmarks/baseline.py): (a) and (c) above and (d), the 240 s point of the
           scaling series (its Coulomb sign's cut-off is chosen by the runs' likelihood), wall
           and CPU time, peak RSS.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "tx40-real"


def _child(args: list[str]) -> None:
    """Run one identification (or only the imports) and print time and peak RSS as JSON."""
    from drivegain.identify.pipeline import IdentifyRequest, run_identify

    if args[0] == "imports":
        print(json.dumps({"seconds": 0.0, "maxrss_kb": _maxrss_kb()}))
        return
    spec = json.loads(args[1])
    req = IdentifyRequest(
        robot=Path(spec["robot"]),
        unloaded=Path(spec["unloaded"]),
        loaded=Path(spec["loaded"]) if spec.get("loaded") else None,
        payload=Path(spec["payload"]) if spec.get("payload") else None,
        gains=spec.get("gains"),
        out=Path(spec["out"]),
        progress=False,
    )
    t0 = time.perf_counter()
    outcome = run_identify(req)
    seconds = time.perf_counter() - t0
    res = outcome.result
    print(
        json.dumps(
            {
                "seconds": seconds,
                "maxrss_kb": _maxrss_kb(),
                "samples_kept": int(sum(res.samples.values())),
                "gains": [float(g) for g in res.gains],
                "relative_error": float(res.final.relative_error),
            }
        )
    )


def _maxrss_kb() -> int:
    """Peak RSS of this process or of its largest worker process (long runs are read in
    forked workers), kB."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(max(own, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss))


def _run_child(kind: str, spec: dict[str, object] | None = None) -> dict[str, float]:
    cmd = [sys.executable, __file__, "--child", kind]
    if spec is not None:
        cmd.append(json.dumps(spec))
    out = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return dict(json.loads(out.stdout.strip().splitlines()[-1]))


def _baseline_seconds() -> float:
    """A fixed workload (QR and SVD of tall matrices, like identification's), best of 3."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((60_000, 80))
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        r = np.linalg.qr(a, mode="r")
        np.linalg.svd(r)
        best = min(best, time.perf_counter() - t0)
    return best


def _write_sim_logs(folder: Path, seconds: float, rate: float, seed: int) -> tuple[Path, Path]:
    from drivegain.config import load_payload, load_robot, load_truth, resource_path
    from drivegain.dynamics.model import build_model
    from drivegain.formats.log import run_metadata
    from drivegain.formats.logwriter import write_run
    from drivegain.identify.synth import exciting_sum_of_sines, simulate_run

    robot = load_robot(resource_path("tx40.toml"))
    model = build_model(robot)
    truth = load_truth(resource_path("sim/tx40-truth.toml"))
    payload = load_payload(resource_path("payloads/calibrated-4590g.toml"))
    rng = np.random.default_rng(seed)
    paths = []
    for label, pay in (("unloaded", None), ("loaded", payload)):
        ex = exciting_sum_of_sines(model, rng, base_frequency_hz=0.1, harmonics=5, candidates=6)
        t = np.arange(0.0, seconds, 1.0 / rate)
        sim_parts = []
        for s in range(0, t.size, 100_000):
            q, qd, qdd = ex.evaluate(t[s : s + 100_000])[:3]
            sim_parts.append(
                simulate_run(
                    model,
                    truth,
                    q,
                    qd,
                    qdd,
                    payload=pay,
                    torque_noise=0.05,
                    quantum=float(np.deg2rad(1e-3)),
                    rng=rng,
                )
            )
        q_m = np.concatenate([p.q for p in sim_parts])
        cur = np.concatenate([p.current_reference for p in sim_parts])
        traj = {"fourier": {"base_frequency_hz": 0.1, "a": [[0.0] * 5] * 6, "b": [[0.0] * 5] * 6}}
        meta = run_metadata(robot, label, pay, 1.0 / rate, "2024-01-01T00:00:00.000Z")
        path = folder / f"{label}-{seconds:g}s-{rate:g}Hz.mcap"
        write_run(
            path,
            meta,
            t,
            q_m,
            cur,
            attachments=[("trajectory.json", "application/json", json.dumps(traj).encode())],
        )
        paths.append(path)
    return paths[0], paths[1]


def _sim_world(seed: int):
    """Robot, model, truth, payload, bases, columns and two excitations for the studies."""
    from drivegain.config import load_payload, load_robot, load_truth, resource_path
    from drivegain.config.robot import WristFriction
    from drivegain.dynamics.model import build_model
    from drivegain.identify.columns import bases_for_forms, stored_columns
    from drivegain.identify.synth import exciting_sum_of_sines

    robot = load_robot(resource_path("tx40.toml"))
    model = build_model(robot)
    bases = bases_for_forms(model)
    rng = np.random.default_rng(seed)
    ex = [
        exciting_sum_of_sines(
            model,
            rng,
            base_frequency_hz=0.2,
            harmonics=5,
            candidates=8,
            base=bases[WristFriction.PHYSICAL],
        )
        for _ in range(2)
    ]
    return (
        robot,
        model,
        load_truth(resource_path("sim/tx40-truth.toml")),
        load_payload(resource_path("payloads/calibrated-4590g.toml")),
        bases,
        stored_columns(robot, bases, [6]),
        ex,
    )


#: encoder quantum of the simulated runs, rad (1e-3°)
QUANTUM = float(np.deg2rad(1e-3))


def _sim_pair(world, rng, seconds: float, rate: float, quantum: float = QUANTUM, **noise):
    from drivegain.identify.prepare import prepare_recording
    from drivegain.identify.signal import default_filter
    from drivegain.identify.synth import simulate_run

    _robot, model, truth, payload, _bases, columns, ex = world
    t = np.arange(0.0, seconds, 1.0 / rate)
    runs = []
    for which, pay, label in ((0, None, "unloaded"), (1, payload, "loaded")):
        q, qd, qdd = ex[which].evaluate(t)[:3]
        sim = simulate_run(model, truth, q, qd, qdd, payload=pay, rng=rng, quantum=quantum, **noise)
        runs.append(
            prepare_recording(
                model,
                columns,
                label=label,
                q=sim.q,
                current=sim.current_reference,
                rate_hz=rate,
                settings=default_filter(rate, 1.0),
                payload=pay,
                period_s=5.0,
            )
        )
    return runs


def coverage_study(seeds: int, seconds: float = 60.0) -> None:
    """Gains over many noise seeds: errors, coverage of the truth by ±2σ, spread of z; with
    the encoder quantum and without it (the same trajectory in every seed, so the quantum's
    error, the same in every seed, shows as a bias that σ does not contain)."""
    from drivegain.identify.blas import limited_blas_threads
    from drivegain.identify.compare import SeedSpread
    from drivegain.identify.procedure import Options, Problem, run_procedure

    with limited_blas_threads(1):
        world = _sim_world(20120701)
        robot, truth, bases = world[0], world[2], world[4]
        for quantum, name in ((QUANTUM, "1e-3° quantum"), (0.0, "no quantum")):
            gains, stds = [], []
            t0 = time.perf_counter()
            for seed in range(seeds):
                rng = np.random.default_rng(10_000 + seed)
                a, b = _sim_pair(world, rng, seconds, 250.0, quantum, torque_noise=0.05)
                res = run_procedure(
                    Problem(robot=robot, bases=bases, unloaded=a, loaded=b),
                    Options(compare_forms=False),
                )
                gains.append(res.gains)
                stds.append(res.gains_std)
            dt = (time.perf_counter() - t0) / seeds
            spread = SeedSpread.of(gains, stds, truth.gains)
            print(
                f"coverage study: {seeds} seeds, 2 x {seconds:g} s at 250 Hz, 0.05 N·m torque "
                f"noise, {name} ({dt:.1f} s per seed): RMS of z "
                f"{float(np.sqrt(np.mean(spread.z**2))):.2f}"
            )
            for line in spread.describe():
                print(f"  {line}")


def sigma_study(seeds: int, seconds: float = 60.0) -> None:
    """The weighting choices of IDIM-WTLS, with current noise of 2 % of each drive's rated
    current (different on every joint), at the paper's α = 5: (1) the paper as printed: σ_j
    from OLS with the a priori gains, one α for all V columns; (2) σ_j iterated on the WTLS
    residuals, one α; (3) iterated σ_j and each drive's V column weighted by its noise
    (drive_noise_weights); and (4) the default: as (3) with α searched on the grid."""
    from drivegain.config.robot import WristFriction
    from drivegain.errors import IdentificationError
    from drivegain.identify.blas import limited_blas_threads
    from drivegain.identify.design import ls_transform as _ls_transform
    from drivegain.identify.design import make_design
    from drivegain.identify.gains import identify_gains
    from drivegain.identify.weighting import joint_sigma
    from drivegain.identify.wtls import wtls_fit

    variants: list[tuple[str, str, dict[str, bool]]] = [
        ("paper", "α = 5, σ_j from OLS with a priori gains", {"iterate": False, "balance": False}),
        ("iterated", "α = 5, σ_j iterated on WTLS residuals", {"balance": False}),
        ("balanced", "α = 5, σ_j iterated, drive columns balanced", {}),
    ]
    with limited_blas_threads(1):
        world = _sim_world(20120701)
        robot, truth, payload, bases = world[0], world[2], world[3], world[4]
        rated = np.array([j.rated_current for j in robot.joints])
        errs: dict[str, list[np.ndarray]] = {key: [] for key, _, _ in variants}
        errs["default"] = []
        for seed in range(seeds):
            a, b = _sim_pair(
                world,
                np.random.default_rng(20_000 + seed),
                seconds,
                250.0,
                current_noise=0.02 * rated,
            )
            bp = bases[WristFriction.PHYSICAL]
            da = make_design(a, bp, WristFriction.PHYSICAL, robot)
            db = make_design(b, bp, WristFriction.PHYSICAL, robot)
            fa, fb = da.factors(), db.factors()
            g0 = robot.apriori_gains
            ts = [_ls_transform(d, s, 1, g0) for d, s in ((da, None), (db, 0))]
            s0 = joint_sigma((da, db), (fa, fb), ts)
            for key, _, kw in variants:
                try:
                    fit = wtls_fit((da, db), (fa, fb), payload, 5.0, s0, g0, **kw)
                    errs[key].append(fit.gains / truth.gains - 1)
                except IdentificationError:
                    errs[key].append(np.full(6, np.nan))
            errs["default"].append(identify_gains(da, db, payload, g0).gains / truth.gains - 1)
    print(
        f"weighting study: {seeds} seeds, 2 x {seconds:g} s at 250 Hz, current noise 2 % of "
        f"rated current ({', '.join(f'{0.02 * r:.2f}' for r in rated)} A)"
    )
    labels = [(key, label) for key, label, _ in variants]
    labels.append(("default", "α searched, σ_j iterated, balanced (default)"))
    for key, label in labels:
        e = 100 * np.array(errs[key])
        failed = int(np.isnan(e[:, 0]).sum())
        if failed == e.shape[0]:
            print(f"  {label:<46} no finite-scale solution in any of the {failed} seeds")
            continue
        print(
            f"  {label:<46} mean error % "
            + ", ".join(f"{v:+.3f}" for v in np.nanmean(e, axis=0))
            + "; rms % "
            + ", ".join(f"{v:.3f}" for v in np.sqrt(np.nanmean(e**2, axis=0)))
            + (f" ({failed} failed)" if failed else "")
        )


def _real_log(work: Path, robot: str) -> Path | None:
    """The real TX-40 recording converted to a log (None when the data is not there)."""
    if not (SHARED / "pos_read_data.csv").is_file():
        return None
    from drivegain.identify.convert import convert_csv

    real = work / "tx40-real.mcap"
    if not real.exists():
        convert_csv(
            SHARED / "pos_read_data.csv",
            SHARED / "curr_data.csv",
            5000.0,
            robot,
            motor_side=True,
            torque=True,
            out=real,
        )
    return real


def compare_with_baseline(ref: str, work: Path, quick: bool, repeats: int) -> None:
    """Whole ``drivegain identify`` processes, this tree beside REF (see the module docstring)."""
    from baseline import best_of, comparison_line, current_command, installed, now_and_then

    from drivegain.config import resource_path

    robot = str(resource_path("tx40.toml"))
    payload = str(resource_path("payloads/calibrated-4590g.toml"))
    cases: list[tuple[str, list[str], bool]] = []
    real = _real_log(work, robot)
    if real is None:
        print("(a) skipped: ../shared/data/tx40-real not found")
    else:
        args = ["identify", "--robot", robot, "--unloaded", str(real), "--gains", "gear-ratios"]
        cases.append(("(a) real TX-40, 45 000 samples", args, True))
    # (d): the scaling series' 240 s point, whose sign cut-off is chosen by likelihood
    sizes = [("(d) 2 x 240 s at 250 Hz, sign choice", 240.0, 250.0)]
    if not quick:
        sizes.append(("(c) 2 x 600 s at 1 kHz (1.2 M msgs)", 600.0, 1000.0))
    for name, seconds, rate in sizes:
        tag = f"{seconds:g}s-{rate:g}Hz"
        a, b = work / f"unloaded-{tag}.mcap", work / f"loaded-{tag}.mcap"
        if not (a.exists() and b.exists()):
            print(f"writing the 2 x {seconds:.0f} s at {rate:g} Hz logs (not timed)...", flush=True)
            a, b = _write_sim_logs(work, seconds, rate, seed=int(seconds))
        args = ["identify", "--robot", robot, "--unloaded", str(a), "--loaded", str(b)]
        cases.append((name, [*args, "--payload", payload], False))
    helptext = subprocess.run(
        [*current_command("drivegain"), "identify", "--help"], capture_output=True, text=True
    ).stdout
    paper = ["--estimator", "paper"] if "--estimator" in helptext else []
    with installed(ref, repeats) as base:
        base_help = subprocess.run(
            [*base.command("drivegain"), "identify", "--help"], capture_output=True, text=True
        ).stdout
        # like for like only where REF has no choice of estimator (its only one is the paper's)
        like_for_like = bool(paper) and "--estimator" not in base_help
        for name, args, plots_too in cases:
            out_now, out_base = ["--out", str(work / "out-now")], ["--out", str(work / "out-base")]
            now, then = now_and_then(base, args, out_now, out_base, repeats)
            print(comparison_line(name, now, then), flush=True)
            same = _same_gains(work / "out-now", work / "out-base")
            print(f"    same gains as the baseline (to 1e-9 relative): {same}")
            if like_for_like:  # this tree's default estimator is not REF's: the paper's
                (like,) = best_of(
                    [[*current_command("drivegain"), *args, *out_now, *paper]], repeats
                )
                print(comparison_line("    now with --estimator paper", like, then), flush=True)
                same = _same_gains(work / "out-now", work / "out-base")
                print(f"    same gains as the baseline (to 1e-9 relative): {same}")
            if plots_too:
                mine = paper if like_for_like else []
                (fast,) = best_of(
                    [[*current_command("drivegain"), *args, *out_now, *mine, "--no-plots"]],
                    repeats,
                )
                print(comparison_line(f"    now {' '.join([*mine, '--no-plots'])}", fast, then))


def read_comparison(work: Path, repeats: int) -> None:
    """``read_run`` of a 600 s, 1 kHz log through its ``/joint_states/columns`` blocks beside
    the same file read from its JSON messages alone (the baseline, same process, alternated)."""
    import os

    from drivegain.formats import logreader

    log = work / "unloaded-600s-1000Hz.mcap"
    if not log.exists():
        print("writing the 2 x 600 s at 1 kHz logs (not timed)...", flush=True)
        log, _ = _write_sim_logs(work, 600.0, 1000.0, seed=600)

    def from_json() -> logreader.RunLog:
        with log.open("rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            return logreader._read_stream(fh, size, log, None, columns=False)

    best = {"blocks": np.inf, "json": np.inf}
    runs = {}
    for _ in range(repeats):
        for name, fn in (("blocks", lambda: logreader.read_run(log)), ("json", from_json)):
            t0 = time.perf_counter()
            runs[name] = fn()
            best[name] = min(best[name], time.perf_counter() - t0)
    same = all(
        np.array_equal(getattr(runs["blocks"], k), getattr(runs["json"], k), equal_nan=True)
        for k in (
            "cycle",
            "t",
            "log_time_ns",
            "position",
            "current_reference",
            "current",
            "setpoint",
        )
    )
    n = runs["blocks"].t.size
    print(
        f"read_run, {n} messages, best of {repeats}: through the blocks {best['blocks']:.2f} s, "
        f"from the JSON messages {best['json']:.2f} s ({best['json'] / best['blocks']:.1f}x); "
        f"identical arrays: {same}; file {log.stat().st_size / 1e6:.0f} MB"
    )


def _same_gains(a: Path, b: Path) -> bool:
    try:
        ga = [g["value"] for g in json.loads((a / "report.json").read_text())["gains"]]
        gb = [g["value"] for g in json.loads((b / "report.json").read_text())["gains"]]
    except (OSError, KeyError, ValueError):
        return False
    return bool(np.allclose(ga, gb, rtol=1e-9, atol=0.0))


def main() -> None:
    from baseline import add_options

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="skip case (c)")
    parser.add_argument("--keep", type=Path, help="keep the logs and reports in this folder")
    parser.add_argument(
        "--study",
        type=int,
        metavar="SEEDS",
        help="instead: coverage and σ studies over SEEDS noise seeds",
    )
    parser.add_argument(
        "--read",
        action="store_true",
        help="instead: reading a 600 s, 1 kHz log through its column blocks and from its JSON",
    )
    add_options(parser, "whole commands of this tree")
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(args.child)
        return
    if args.read:
        work = args.keep or Path(tempfile.mkdtemp(prefix="bench-identify-"))
        work.mkdir(parents=True, exist_ok=True)
        read_comparison(work, max(args.repeats, 3))
        return
    if args.baseline_ref:
        work = args.keep or Path(tempfile.mkdtemp(prefix="bench-identify-"))
        work.mkdir(parents=True, exist_ok=True)
        try:
            compare_with_baseline(args.baseline_ref, work, args.quick, args.repeats)
        finally:
            if not args.keep:
                import shutil

                shutil.rmtree(work, ignore_errors=True)
        return
    if args.study:
        coverage_study(args.study)
        sigma_study(max(5, args.study // 5))
        return
    from drivegain.config import resource_path

    robot = str(resource_path("tx40.toml"))
    payload = str(resource_path("payloads/calibrated-4590g.toml"))
    work = args.keep or Path(tempfile.mkdtemp(prefix="bench-identify-"))
    work.mkdir(parents=True, exist_ok=True)
    base_s = _baseline_seconds()
    imports = _run_child("imports")
    print(
        f"baseline workload (QR+SVD of 60000x80): {base_s:.3f} s; "
        f"process with the pipeline imported: {imports['maxrss_kb'] / 1024:.0f} MB peak RSS"
    )
    print(
        f"{'case':<34}{'raw samples':>12}{'kept':>8}{'time s':>9}{'× base':>8}"
        f"{'mem MB':>9}{'MB/1e5 raw':>11}"
    )
    rows = []

    def report(name: str, raw: int, spec: dict[str, object]) -> dict[str, float]:
        res = _run_child("run", spec)
        mem = (res["maxrss_kb"] - imports["maxrss_kb"]) / 1024
        rows.append((name, raw, res["seconds"], mem))
        print(
            f"{name:<34}{raw:>12}{int(res['samples_kept']):>8}{res['seconds']:>9.2f}"
            f"{res['seconds'] / base_s:>8.1f}{mem:>9.0f}{1e5 * mem / raw:>11.1f}",
            flush=True,
        )
        return res

    real = _real_log(work, robot)
    if real is not None:
        report(
            "(a) real TX-40, 5 kHz, 9 s",
            45_000,
            {
                "robot": robot,
                "unloaded": str(real),
                "gains": "gear-ratios",
                "out": str(work / "out-a"),
            },
        )
    else:
        print("(a) skipped: ../shared/data/tx40-real not found")

    series = [30.0, 60.0, 120.0, 240.0]
    timings = []
    for seconds in series:
        a, b = _write_sim_logs(work, seconds, 250.0, seed=int(seconds))
        raw = 2 * int(seconds * 250)
        name = (
            f"(b) 2 x {seconds:g} s at 250 Hz"
            if seconds == 60.0
            else f"    2 x {seconds:g} s at 250 Hz"
        )
        res = report(
            name,
            raw,
            {
                "robot": robot,
                "unloaded": str(a),
                "loaded": str(b),
                "payload": payload,
                "out": str(work / f"out-b{seconds:g}"),
            },
        )
        timings.append((raw, res["seconds"], rows[-1][3]))
        if seconds == 60.0:
            verdict = "met" if res["seconds"] < 10.0 else "MISSED"
            print(f"    target (b) < 10 s: {verdict}; gains {np.round(res['gains'], 3)}")
    if not args.quick:
        a, b = _write_sim_logs(work, 600.0, 1000.0, seed=600)
        raw = 2 * 600_000
        res = report(
            "(c) 2 x 600 s at 1 kHz",
            raw,
            {
                "robot": robot,
                "unloaded": str(a),
                "loaded": str(b),
                "payload": payload,
                "out": str(work / "out-c"),
            },
        )
        timings.append((raw, res["seconds"], rows[-1][3]))
    raw_a = np.array([t[0] for t in timings], dtype=float)
    sec_a = np.array([t[1] for t in timings])
    mem_a = np.array([max(t[2], 1.0) for t in timings])
    k_t = np.polyfit(np.log(raw_a), np.log(sec_a), 1)[0]
    k_m = np.polyfit(np.log(raw_a), np.log(mem_a), 1)[0]
    print(
        f"growth with raw samples (log-log slope over the simulated cases): time ~ N^{k_t:.2f}, "
        f"memory above the imports ~ N^{k_m:.2f}"
    )
    if not args.keep:
        import shutil

        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
