"""How long a waking cycle thread waits for the interpreter lock while the recorder computes.

One command: ``python benchmarks/bench_handoff.py [--seconds S] [--repeats K]``.

A thread sleeps 1 ms and wakes, over and over, at SCHED_FIFO 80 when granted (as the cycle
thread of a realtime session), while another thread of the same process writes a log as fast as
it can through :class:`drivegain.formats.logwriter.LogWriter` (JSON, raw, ROS 2 messages and
zstd chunks: the recorder's work, without pause). Its wake-up delay beyond the 1 ms is measured
with the interpreter's default switch interval (the baseline, measured in the same run) and
with the realtime policy's (:data:`drivegain.acquire.rig.REALTIME_SWITCH_INTERVAL_S`),
alternated, and with no writer at all (the machine's own wake-up latency). The writer's
throughput is printed too: a shorter interval costs it more hand-offs.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from drivegain.acquire.rig import REALTIME_SWITCH_INTERVAL_S
from drivegain.formats.log import RunMetadata
from drivegain.formats.logwriter import LogWriter

NAMES = [f"j{i}" for i in range(1, 7)]


def _waiter(stop: threading.Event, delays: list[int], fifo: list[bool]) -> None:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(80))
        fifo.append(True)
    except OSError:
        fifo.append(False)
    while not stop.is_set():
        t = time.perf_counter_ns()
        time.sleep(0.001)
        delays.append(time.perf_counter_ns() - t - 1_000_000)


def measure(seconds: float, interval: float | None, writer: bool) -> tuple[np.ndarray, float, bool]:
    """Wake-up delays (µs) of the sleeping thread, cycles written per second, FIFO granted."""
    before = sys.getswitchinterval()
    if interval is not None:
        sys.setswitchinterval(interval)
    stop, delays, fifo = threading.Event(), [], []
    thread = threading.Thread(target=_waiter, args=(stop, delays, fifo))
    cycles = 0
    try:
        with tempfile.TemporaryDirectory() as tmp:
            meta = RunMetadata("bench", "unloaded", "none", NAMES, 0.004, "2026-01-01T00:00:00Z")
            log = LogWriter(Path(tmp) / "run.mcap", meta)
            values = np.linspace(-1.0, 1.0, 6)
            raw = {
                f"node{i}": {"position": 123456, "current": 42, "status": 0x1237} for i in range(6)
            }
            thread.start()
            end = time.perf_counter() + seconds
            while time.perf_counter() < end:
                if writer:
                    log.write_joint_state(
                        cycle=cycles,
                        t=cycles * 0.004,
                        log_time_ns=cycles * 4_000_000,
                        position=values,
                        current_reference=values,
                        current=values,
                        setpoint=values,
                    )
                    log.write_raw(cycle=cycles, log_time_ns=cycles * 4_000_000, raw=raw)
                    cycles += 1
                else:
                    time.sleep(0.01)
            stop.set()
            thread.join()
            log.finish()
    finally:
        sys.setswitchinterval(before)
    return np.asarray(delays) / 1e3, cycles / seconds, bool(fifo and fifo[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="per measurement")
    parser.add_argument("--repeats", type=int, default=2, help="alternated measurements each")
    args = parser.parse_args()
    default = sys.getswitchinterval()
    cases = [
        ("no writer (the machine)", None, False),
        (f"writer, default interval {default * 1e3:g} ms", None, True),
        (
            f"writer, realtime {REALTIME_SWITCH_INTERVAL_S * 1e3:g} ms",
            REALTIME_SWITCH_INTERVAL_S,
            True,
        ),
    ]
    results: dict[str, list[tuple[np.ndarray, float]]] = {name: [] for name, _, _ in cases}
    granted = True
    for _ in range(args.repeats):
        for name, interval, writer in cases:
            delays, rate, fifo = measure(args.seconds, interval, writer)
            results[name].append((delays, rate))
            granted = granted and fifo
    print(
        f"waking thread at SCHED_FIFO 80: {'granted' if granted else 'refused (normal priority)'}"
    )
    head = f"{'case':<34}{'wake-ups':>9}{'p50 µs':>9}{'p99 µs':>9}{'max µs':>9}"
    print(f"{head}{'> 2.5 ms':>9}{'cycles/s':>10}")
    p99 = {}
    for name, _, _ in cases:
        d = np.concatenate([r[0] for r in results[name]])
        rate = float(np.mean([r[1] for r in results[name]]))
        p99[name] = float(np.percentile(d, 99))
        print(
            f"{name:<34}{d.size:>9}{np.median(d):>9.0f}{p99[name]:>9.0f}{d.max():>9.0f}"
            f"{int((d > 2500).sum()):>9}{rate if rate else float('nan'):>10.0f}"
        )
    base, ours = cases[1][0], cases[2][0]
    ratio = p99[base] / p99[ours]
    print(f"p99 wake-up delay behind the writer: {ratio:.1f} x shorter at the realtime interval")


if __name__ == "__main__":
    main()
