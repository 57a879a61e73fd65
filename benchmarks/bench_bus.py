"""Benchmark of the mocked CAN bus: master + 6 simulated drives on python-can's virtual bus.

1. Real time: for each cycle rate, run the master against the simulated TX-40 in ``realtime``
   clock for ``--seconds`` (default 3 s per rate for a quick look; use ``--seconds 60`` for the
   figure of record) and count lost cycles (a cycle is lost when its TPDOs are not all in before
   the next SYNC is due, or the master raises). Reports the SYNC jitter (send time minus the
   ideal schedule), SYNC-to-last-TPDO latency (p50/p99), CPU use of the process, and what the
   same exchange would load a real 1 Mbit/s bus with (the virtual bus has no bit timing).
2. Lockstep: speed-up of ``--lockstep-seconds`` of simulated time over real time.

Ratios are to the 250 Hz run of the same invocation (the project's default period).

    python benchmarks/bench_bus.py [--seconds 3] [--rates 100,250,500,1000,2000]
"""

from __future__ import annotations

import argparse
import itertools
import os
import time
from dataclasses import dataclass

import numpy as np

from drivegain.config import Robot, load_robot, resource_path
from drivegain.drivers.bus import BusConfig, open_network
from drivegain.drivers.master import Master, Timeouts
from drivegain.drivers.sim import SimConfig, SimulatedCell
from drivegain.errors import DriveError

_channels = itertools.count()


@dataclass
class RealtimeResult:
    rate_hz: float
    cycles: int
    lost: int
    jitter_p50_us: float
    jitter_p99_us: float
    latency_p50_us: float
    latency_p99_us: float
    cpu_percent: float  # of one core
    bus_load_percent: float  # of a real 1 Mbit/s bus


def motion(q0: np.ndarray, t: float) -> np.ndarray:
    """A gentle motion of every joint, so that the physics and the drives do real work."""
    return q0 + 0.1 * (1.0 - np.cos(2 * np.pi * 0.5 * t)) * np.ones_like(q0)


def realtime_run(robot: Robot, rate_hz: float, seconds: float) -> RealtimeResult:
    period = 1.0 / rate_hz
    cfg = BusConfig("virtual", f"bench-{os.getpid()}-{next(_channels)}")
    # A TPDO later than the period means the cycle is lost: that is the deadline.
    timeouts = Timeouts(tpdo_s=period, heartbeat_s=0.5)
    cell = SimulatedCell(robot, cfg, SimConfig(clock="realtime"), period)
    cell.start()
    network = open_network(cfg)
    master = Master(robot, network, period_s=period, timeouts=timeouts)
    jitter, latency = [], []
    lost = 0
    n = round(seconds * rate_hz)
    try:
        master.boot()
        master.enable()
        q0 = master.read_positions()
        cpu0, wall0 = time.process_time(), time.monotonic()
        due = wall0 + period
        for k in range(n):
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            sent = time.monotonic()
            jitter.append(sent - due)
            try:
                sample = master.cycle(motion(q0, k * period))
                latency.append(sample.latency_s)
            except DriveError:
                lost += 1
                continue
            finally:
                due += period
            if time.monotonic() > due:  # the next SYNC cannot leave on time
                lost += 1
        cpu = (time.process_time() - cpu0) / (time.monotonic() - wall0)
    finally:
        master.close()
        network.disconnect()
        cell.stop()
    load = master.bus_load(1_000_000).load
    j = np.abs(np.array(jitter)) * 1e6
    lat = np.array(latency) * 1e6 if latency else np.array([np.nan])
    return RealtimeResult(
        rate_hz=rate_hz,
        cycles=n,
        lost=lost,
        jitter_p50_us=float(np.percentile(j, 50)),
        jitter_p99_us=float(np.percentile(j, 99)),
        latency_p50_us=float(np.percentile(lat, 50)),
        latency_p99_us=float(np.percentile(lat, 99)),
        cpu_percent=100.0 * cpu,
        bus_load_percent=100.0 * load,
    )


def lockstep_speedup(robot: Robot, sim_seconds: float, period: float = 0.004) -> float:
    cfg = BusConfig("virtual", f"bench-{os.getpid()}-{next(_channels)}")
    cell = SimulatedCell(robot, cfg, SimConfig(clock="lockstep"), period)
    cell.start()
    network = open_network(cfg)
    # Lockstep has no deadline: only a stalled machine would hit this limit.
    master = Master(robot, network, period_s=period, timeouts=Timeouts(tpdo_s=2.0))
    try:
        master.boot()
        master.enable()
        q0 = master.read_positions()
        n = round(sim_seconds / period)
        start = time.monotonic()
        for k in range(n):
            master.cycle(motion(q0, k * period))
        wall = time.monotonic() - start
    finally:
        master.close()
        network.disconnect()
        cell.stop()
    return sim_seconds / wall


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="real-time run per rate, s")
    parser.add_argument(
        "--rates", default="100,250,500,1000,2000", help="cycle rates to try, Hz (comma list)"
    )
    parser.add_argument(
        "--lockstep-seconds", type=float, default=10.0, help="simulated time of the lockstep run"
    )
    args = parser.parse_args()
    robot = load_robot(resource_path("tx40.toml"))
    rates = sorted(float(r) for r in args.rates.split(","))
    if 250.0 not in rates:
        rates = sorted([*rates, 250.0])
    print(
        f"master + 6 simulated drives, virtual bus, {args.seconds:g} s per rate, "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} before the run"
    )
    # The 250 Hz run first: it is the baseline of the ratios.
    order = [250.0] + [r for r in rates if r != 250.0]
    by_rate = {}
    for rate in order:
        by_rate[rate] = realtime_run(robot, rate, args.seconds)
        print(f"  ... {rate:.0f} Hz done", flush=True)
    results = [by_rate[r] for r in rates]
    print(
        f"{'rate Hz':>8} {'cycles':>7} {'lost':>5} {'jitter p50/p99 us':>18} "
        f"{'latency p50/p99 us':>19} {'CPU %':>6} {'x CPU@250':>9} {'1Mbit bus %':>11}"
    )
    base = by_rate[250.0]
    for r in results:
        print(
            f"{r.rate_hz:8.0f} {r.cycles:7d} {r.lost:5d} "
            f"{r.jitter_p50_us:8.0f} / {r.jitter_p99_us:7.0f} "
            f"{r.latency_p50_us:9.0f} / {r.latency_p99_us:7.0f} "
            f"{r.cpu_percent:6.1f} {r.cpu_percent / base.cpu_percent:9.2f} "
            f"{r.bus_load_percent:11.0f}"
        )
    clean = [r.rate_hz for r in results if r.lost == 0]
    best = max(clean) if clean else None
    if best is None:
        print("no rate ran without a lost cycle")
    else:
        print(
            f"highest rate without a lost cycle: {best:.0f} Hz ({best / 250.0:.1f} x the 250 Hz "
            f"default; a real 1 Mbit/s bus allows "
            f"{base.rate_hz / (base.bus_load_percent / 100):.0f} Hz for this mapping)"
        )
    speedup = lockstep_speedup(robot, args.lockstep_seconds)
    print(f"lockstep at 250 Hz: {args.lockstep_seconds:g} s simulated, {speedup:.1f} x real time")
    print(f"load average {os.getloadavg()[0]:.1f} after the run (other processes share the CPUs)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
