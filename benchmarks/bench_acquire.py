"""Benchmark of the acquisition: realtime cycle timing, lockstep speed, memory of a long run.

One command::

    python benchmarks/bench_acquire.py                 # 60 s realtime runs, 10-minute memory run
    python benchmarks/bench_acquire.py --duration 10 --memory-minutes 2   # shorter
    python benchmarks/bench_acquire.py --baseline-ref [REF]   # lockstep acquire beside REF

What it measures, each against a baseline taken in the same run on the same machine:

1. Realtime, 250 Hz and 400 Hz, 6 simulated drives, a full session (cycle loop, supervision,
   recorder thread writing MCAP) on a slow 0.5 Hz excitation, with the pipelined master (SYNC k,
   then the TPDOs of cycle k−1; the realtime default), and with ``--same-cycle`` also the
   same-cycle master (SYNC k, then wait for cycle k's TPDOs) for comparison. The simulated drives
   run in a child process on the ``drivegain-ipc`` bus (``--sim-host process``, default; as real
   drives they then take no CPU time or interpreter lock from the master) or in the master's
   process on the virtual bus (``--sim-host thread``). The cycle thread asks for SCHED_FIFO
   priority 80 as the hardware configuration does (``--rt-priority``; whether it was granted is
   printed). Baseline, in the same run and for as long: the same absolute-deadline loop with no
   bus work, at the same priority, while the same simulated drives run enabled beside it (what
   the machine's scheduler alone gives under that load). Printed for each: lost cycles (deadline
   missed by more than a period, or TPDOs later than the SYNC that waited for them: one period
   after their own SYNC for the same-cycle master, two for the pipelined one), late TPDOs (last
   TPDO of a cycle more than a period after its SYNC, recorded; + dropped ones), p50/p99 SYNC
   jitter (deviation of the SYNC interval from the period) and p99 as a fraction of the period,
   SYNC-to-last-TPDO latency, CPU of the master's process and of the drives' process; then
   whether the targets hold: lost ≤ the bare loop's + 1 per 10 000 cycles, p99 jitter ≤ 1.5 ×
   the bare loop's.
2. Lockstep, 250 Hz: simulated seconds per wall second of a full session, against the bare
   ``Master.cycle`` loop without session and recorder.
3. Memory: a long lockstep session (10 simulated minutes by default): resident memory sampled
   every 10 simulated seconds, its growth after the first minutes and the peak.
4. Simulated clock, realtime, 250 Hz, 6 simulated drives in the master's process: how closely the
   drives' simulated time follows the wall clock. At every SYNC, simulated time minus the SYNC's
   wall-clock time, about their median: p50, p99 and max of its size, and how far the two clocks
   moved apart across a 0.1 s pause of the master in the middle (the simulation must go on
   through it). The test suite checks only that the simulated clock advances and goes on
   through a pause; these figures are the timing (0.5-0.7 ms seen on a quiet machine, 16 ms
   outliers with both cores saturated).

400 Hz needs about 100 % of a 1 Mbit/s bus with 6 drives (worst-case stuffing; 500 Hz 125 %),
which a session refuses; the simulated buses have no bitrate, so for the software timing this
script turns the refusal into a printed note. Real hardware that fast needs fewer drives per bus.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import resource
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from drivegain.acquire import request as request_mod
from drivegain.acquire import session as session_mod
from drivegain.acquire.config import AcquisitionConfig, load_acquisition_config
from drivegain.acquire.logs import quiet_libraries
from drivegain.acquire.pacing import RealtimePacer
from drivegain.acquire.request import RunRequest, prepare_run
from drivegain.acquire.rig import Rig, realtime_policy
from drivegain.acquire.session import Session
from drivegain.acquire.stats import LoopStats
from drivegain.config import load_robot, resource_path
from drivegain.drivers.bus import BusConfig, BusLoad, bus_load
from drivegain.drivers.ipcbus import INTERFACE as IPC_INTERFACE
from drivegain.drivers.master import Timeouts
from drivegain.drivers.realtime import RealtimePolicy
from drivegain.drivers.sim import SimulatedCell
from drivegain.errors import ConfigError, DriveError
from drivegain.excite.trajectory import save_trajectory, trajectory_document
from drivegain.formats.fourier import FourierTrajectory


def rss_mb() -> float:
    """Resident set size now, MiB (Linux /proc)."""
    with open("/proc/self/statm") as fh:
        pages = int(fh.read().split()[1])
    return pages * resource.getpagesize() / 2**20


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def trajectory_for(duration_s: float, folder: Path) -> Path:
    """The shipped excitation with enough periods to last about ``duration_s``."""
    doc = json.loads(resource_path("tx40-excitation.json").read_text())
    period = 1.0 / float(doc["fourier"]["base_frequency_hz"])
    doc["periods"] = max(1, math.ceil(duration_s / period))
    path = folder / f"traj-{doc['periods']}.json"
    path.write_text(json.dumps(doc))
    return path


def gentle_trajectory(duration_s: float, folder: Path) -> Path:
    """A slow excitation (0.5 Hz, 2 harmonics, |qd| < 1.2 rad/s) lasting about ``duration_s``.

    Realtime timing is measured on a machine shared with other work: with the shipped
    near-the-limits excitation a stall of several periods makes the drives catch up faster than
    the velocity limit, and supervision (rightly) stops the run before the timing is measured.
    """
    robot = load_robot(resource_path("tx40.toml"))
    rng = np.random.default_rng(0)
    f = FourierTrajectory(
        0.5,
        np.array([0.1, -0.2, 0.3, 0.0, 0.4, 0.0]),
        rng.uniform(-0.3, 0.3, (robot.n, 2)),
        rng.uniform(-0.3, 0.3, (robot.n, 2)),
        max(1, math.ceil(duration_s * 0.5)),
    )
    return save_trajectory(
        folder / f"gentle-{f.periods}.json", trajectory_document(f, robot, {"cond": 0.0})
    )


def config(
    clock: str,
    period_s: float,
    folder: Path,
    *,
    sim_host: str = "thread",
    rt_priority: int = 0,
    spin_s: float = 0.0,
) -> AcquisitionConfig:
    base = load_acquisition_config(resource_path("acquire-sim.toml"))
    assert base.simulation is not None
    sim = dataclasses.replace(base.simulation, clock=clock, history_s=1.0)
    bus = base.bus
    if sim_host == "process":
        bus = BusConfig(IPC_INTERFACE, str(folder / f"bus-{time.monotonic_ns()}.sock"), bus.bitrate)
    return dataclasses.replace(
        base,
        period_s=period_s,
        simulation=sim,
        bus=bus,
        rt_priority=rt_priority,
        spin_s=spin_s,
        # a late TPDO is counted (late_cycles), not fatal, and so are missed deadlines
        # (overruns): the benchmark measures them
        tpdo_timeout_s=0.2 if clock == "realtime" else 2.0,
        supervision=dataclasses.replace(base.supervision, max_overruns=1_000_000),
    )


def children_cpu_s() -> float:
    """CPU time of the reaped child processes so far (the simulated drives' process), s."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


# the same check runs before the bus is touched (request) and on the booted drives (session)
_original_check = session_mod.check_bus_load
_CHECKERS = (request_mod, session_mod)
_notes: list[str] = []


@functools.wraps(_original_check)
def _virtual_bus_check(
    n_nodes: int, period_s: float, bitrate: int, **kw: Any
) -> tuple[BusLoad, str | None]:
    """The session's bus-load check, with a refusal turned into a note (virtual bus only)."""
    try:
        return _original_check(n_nodes, period_s, bitrate, **kw)
    except ConfigError as exc:
        _notes.append(f"bus-load check bypassed for the simulated bus: {exc.message}")
        return (kw.get("load") or bus_load(n_nodes, period_s, bitrate)), None


def run_session(
    cfg: AcquisitionConfig,
    trajectory: Path,
    out: Path,
    sample_every: int = 0,
    pipelined: bool | None = None,
) -> tuple[Session, float, float, list[tuple[float, float]]]:
    """One full session; returns it, wall time, CPU time and (sim time, RSS) samples."""
    for mod in _CHECKERS:
        mod.check_bus_load = _virtual_bus_check
    try:
        prepared = prepare_run(cfg, RunRequest(trajectory, out))
        samples: list[tuple[float, float]] = []

        def on_cycle(s: Session) -> None:
            if sample_every and s.cycle % sample_every == 0:
                samples.append((s.t, rss_mb()))

        rig = _rig(cfg)
        with rig as master:
            session = Session(
                cfg, master, prepared, on_cycle=on_cycle, policy=rig.policy, pipelined=pipelined
            )
            session.plan()
            w0, c0 = time.perf_counter(), time.process_time()
            session.run()
            wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    finally:
        for mod in _CHECKERS:
            mod.check_bus_load = _original_check
    return session, wall, cpu, samples


#: ``--switch-interval-s``: the interpreter's switch interval of the rigs (None: left as it is).
_SWITCH_INTERVAL_S: float | None = None


def _rig(cfg: AcquisitionConfig) -> Rig:
    """The configuration's rig, with ``--switch-interval-s`` in its realtime policy."""
    policy = dataclasses.replace(realtime_policy(cfg), switch_interval_s=_SWITCH_INTERVAL_S)
    return Rig(cfg, policy=policy)


def baseline_pacing(period_s: float, seconds: float, policy: RealtimePolicy) -> LoopStats:
    """The absolute-deadline loop alone (no bus), on the sessions' cycle-thread scheduling:
    the scheduler's own jitter."""
    stats = LoopStats(period_s=period_s, clock="realtime")
    pacer = RealtimePacer(period_s, stats)
    with policy.cycle_thread():
        pacer.start()
        last = None
        for k in range(int(seconds / period_s)):
            pacer.wait(k)
            stats.cycles += 1
            now = time.monotonic_ns()
            if last is not None:
                stats.sync_dev.add(abs(now - last - round(period_s * 1e9)))
            last = now
    return stats


def baseline_under_load(cfg: AcquisitionConfig, seconds: float) -> LoopStats:
    """The bare loop while the same simulated drives run enabled (holding position) beside it."""
    rig = _rig(cfg)
    with rig as master:
        master.enable()
        return baseline_pacing(cfg.period_s, seconds, rig.policy)


def fifo_granted(cfg: AcquisitionConfig) -> str:
    """Whether the sessions' cycle thread gets its SCHED_FIFO priority here."""
    with realtime_policy(cfg).cycle_thread() as fifo:
        return fifo.describe()


_RT_HEADER = (
    f"{'rate':>5} {'loop':<11} {'cycles':>7} {'lost':>5} {'late':>5} {'drop':>5} "
    f"{'jit p50':>8} {'jit p99':>8} {'p99/T':>6} {'lat p99':>8} {'CPU':>6} {'CPU sim':>7}"
)


def _rt_line(rate: float, loop: str, st: LoopStats, lost: int, rest: str) -> str:
    p50, p99 = st.sync_dev.quantile(0.5) / 1e3, st.sync_dev.quantile(0.99) / 1e3
    return (
        f"{rate:5g} {loop:<11} {st.cycles:7d} {lost:5d} {rest} {p50:7.0f}µ {p99:7.0f}µ "
        f"{p99 / (st.period_s * 1e6):6.1%}"
    )


def _rt_session(
    cfg: AcquisitionConfig, traj: Path, out: Path, sim_host: str, pipelined: bool
) -> tuple[Session, str] | str:
    """One realtime session: (session, the rest of its printed line), or why it stopped."""
    child0 = children_cpu_s()
    try:
        s, wall, cpu, _ = run_session(cfg, traj, out, pipelined=pipelined)
    except Exception as exc:  # a lost TPDO ends the run: report it as such
        return f"run stopped: {exc}"
    cpu_sim = (children_cpu_s() - child0) / wall if sim_host == "process" else float("nan")
    st = s.stats
    lat = st.service.quantile(0.99) / 1e3
    return s, f"{lat:7.0f}µ {cpu / wall:6.1%} {cpu_sim:7.1%}"


def realtime(
    duration: float,
    rates: list[float],
    folder: Path,
    sim_host: str,
    rt_priority: int,
    same_cycle: bool = False,
    spin_s: float = 0.0,
) -> None:
    where = "their own process" if sim_host == "process" else "the master's process"
    probe = config("realtime", 1.0 / rates[0], folder, sim_host=sim_host, rt_priority=rt_priority)
    print(
        f"\n== realtime, 6 simulated drives in {where}, {duration:g} s of excitation per rate, "
        f"SCHED_FIFO {rt_priority}: {fifo_granted(probe)}, spin_s {spin_s:g}, "
        f"switch interval {_SWITCH_INTERVAL_S or sys.getswitchinterval():g} s =="
    )
    print(_RT_HEADER)
    traj = gentle_trajectory(duration, folder)
    loops = [("pipelined", True)] + ([("same cycle", False)] if same_cycle else [])
    for rate in rates:
        period = 1.0 / rate
        cfg = config(
            "realtime", period, folder, sim_host=sim_host, rt_priority=rt_priority, spin_s=spin_s
        )
        # the bare loop for as long as the sessions' excitation, beside the same drives
        base = baseline_under_load(cfg, duration)
        blank = f"{'-':>5} {'-':>5}"
        print(_rt_line(rate, "bare loop", base, base.overruns, blank))
        base_p99 = base.sync_dev.quantile(0.99)
        for name, pipelined in loops:
            got = _rt_session(
                cfg, traj, folder / f"rt-{rate:g}-{name[0]}.mcap", sim_host, pipelined
            )
            if isinstance(got, str):
                print(f"{rate:5g} {name:<11} {got}")
                continue
            s, rest = got
            st = s.stats
            lost = st.overruns + s.held_cycles
            dropped = sum(st.late_tpdo.values())
            line = _rt_line(rate, name, st, lost, f"{st.late_cycles:5d} {dropped:5d}")
            print(f"{line} {rest}")
            allowed = base.overruns + st.cycles / 10_000
            p99 = st.sync_dev.quantile(0.99)
            ratio = p99 / base_p99 if base_p99 else float("inf")
            print(
                f"{'':5} {'':11} lost {st.overruns} missed deadlines + {s.held_cycles} held by "
                f"TPDOs; target lost ≤ {allowed:.1f}: {'met' if lost <= allowed else 'MISSED'}, "
                f"p99 jitter {ratio:.2f} × the bare loop's (≤ 1.5: "
                f"{'met' if ratio <= 1.5 else 'MISSED'})"
            )
    for note in dict.fromkeys(_notes):
        print(f"  note: {note}")
    print(
        "  lost: deadlines missed by more than a period + cycles whose TPDOs held the next SYNC "
        "back;\n  late: cycles whose last TPDO came more than a period after their SYNC "
        "(recorded all the same when\n  pipelined), drop: TPDOs that came after their cycle "
        "was over; jit: |SYNC interval − period|;\n  lat: SYNC to the last TPDO; CPU: the "
        "master's process (session, recorder, bus reader),\n  CPU sim: the simulated drives' "
        "process; both in % of one core"
    )


def virtual_bus_ceiling(cycles: int) -> tuple[float, float]:
    """python-can's virtual bus with canopen networks (a notifier thread each) and no work at
    all: (frames/s one way, in bursts of 1000; SYNC cycles/s of the lockstep exchange's shape,
    6 RPDOs + SYNC out and 12 TPDOs back, the next cycle once all 12 are in)."""
    import threading

    import can

    from drivegain.drivers.bus import open_network

    channel = f"bench-ceiling-{time.monotonic_ns()}"
    cfg = BusConfig("virtual", channel)
    master, drives = open_network(cfg), open_network(cfg)
    try:
        got = [0]
        done = threading.Event()
        want = [0]

        class Count(can.Listener):
            def on_message_received(self, msg: can.Message) -> None:
                got[0] += 1
                if got[0] >= want[0]:
                    done.set()

        assert master.notifier is not None
        master.notifier.add_listener(Count())
        # one way: frames/s from the drives' side to the master's listener
        want[0], burst = 1000, 1000
        w0 = time.perf_counter()
        for _ in range(burst):
            drives.send_message(0x181, bytes(8))
        done.wait(30.0)
        one_way = burst / (time.perf_counter() - w0)
        # the exchange: the drives answer each SYNC with 12 frames
        drives.subscribe(
            0x80, lambda *_: [drives.send_message(0x181 + k, bytes(8)) for k in range(12)]
        )
        w0 = time.perf_counter()
        for _ in range(cycles):
            got[0], want[0] = 0, 12
            done.clear()
            for node in range(1, 7):
                master.send_message(0x200 + node, bytes(8))
            master.send_message(0x80, b"\x01")
            done.wait(5.0)
        return one_way, cycles / (time.perf_counter() - w0)
    finally:
        master.disconnect()
        drives.disconnect()


def lockstep(seconds: float, folder: Path) -> None:
    print(f"\n== lockstep, 250 Hz, about {seconds:g} simulated s ==")
    cfg = config("lockstep", 0.004, folder)
    traj = trajectory_for(seconds, folder)
    s, wall, cpu, _ = run_session(cfg, traj, folder / "lockstep.mcap")
    sim_s = s.stats.cycles * cfg.period_s
    # baseline: the bare master loop, same cell, no session, no recorder
    n = s.stats.cycles
    with Rig(cfg) as master:
        master.enable()
        q = master.read_positions()
        w0 = time.perf_counter()
        for _ in range(n):
            master.cycle(q)
        bare = time.perf_counter() - w0
    print(f"session + recorder: {sim_s:7.1f} simulated s in {wall:6.1f} s: {sim_s / wall:5.2f} x")
    print(f"bare Master.cycle : {sim_s:7.1f} simulated s in {bare:6.1f} s: {sim_s / bare:5.2f} x")
    print(f"session overhead  : {wall / bare:5.2f} x the bare loop; CPU {cpu / wall:.0%}")
    one_way, exchange = virtual_bus_ceiling(min(n, 5000))
    print(
        f"python-can virtual bus, no work: {one_way:,.0f} frames/s one way; the exchange's "
        f"19 frames per SYNC at most {exchange:,.0f} cycles/s = {exchange * cfg.period_s:5.2f} x "
        f"real time at 250 Hz (lockstep reaches {sim_s / wall / (exchange * cfg.period_s):.0%} "
        "of it)"
    )


def memory(minutes: float, folder: Path) -> None:
    print(f"\n== memory, lockstep session of about {minutes:g} simulated minutes ==")
    cfg = config("lockstep", 0.004, folder)
    traj = trajectory_for(minutes * 60.0, folder)
    before = rss_mb()
    s, wall, _, samples = run_session(
        cfg, traj, folder / "memory.mcap", sample_every=round(10.0 / cfg.period_s)
    )
    t = np.array([x[0] for x in samples])
    rss = np.array([x[1] for x in samples])
    late = t >= min(120.0, t[-1] / 2)
    slope = float(np.polyfit(t[late] / 60.0, rss[late], 1)[0]) if late.sum() > 2 else float("nan")
    size = (folder / "memory.mcap").stat().st_size / 2**20
    print(f"{s.stats.cycles} cycles, {t[-1] / 60:.1f} simulated min in {wall:.0f} s wall")
    print(
        f"RSS before {before:.1f} MiB, at 1 min {np.interp(60.0, t, rss):.1f} MiB, at the end "
        f"{rss[-1]:.1f} MiB; growth after minute {t[late][0] / 60:.0f}: {slope:+.2f} MiB/min"
    )
    print(f"peak RSS of the process {peak_rss_mb():.1f} MiB; log {size:.1f} MiB")
    print(f"recorder queue high-water mark: {s._recorder.high_water if s._recorder else '?'}")


def simulated_clock(cycles: int, folder: Path) -> None:
    """Simulated time against the wall clock at every SYNC, with a 0.1 s pause in the middle."""
    period, pause_s, pause_at = 0.004, 0.1, cycles // 2
    print(f"\n== simulated clock, realtime, 250 Hz, {cycles} SYNCs, {pause_s:g} s pause ==")
    cfg = config("realtime", period, folder)
    assert cfg.simulation is not None
    history_s = cycles * period + pause_s + 1.0  # every SYNC of the measurement is kept
    cfg = dataclasses.replace(
        cfg, simulation=dataclasses.replace(cfg.simulation, history_s=history_s)
    )
    # a late answer or heartbeat is what is measured here, not a fault
    patient = Timeouts(boot_s=5.0, sdo_s=2.0, state_s=2.0, heartbeat_s=3.0, tpdo_s=2.0)
    rig = Rig(cfg, timeouts=patient)
    try:
        with rig as master:
            master.enable()
            q = master.read_positions()
            sync_ns = []
            next_t = time.monotonic()
            for k in range(cycles):
                sync_ns.append(master.cycle(q).sync_time_ns)
                if k == pause_at:
                    time.sleep(pause_s)  # real time goes on, and so must the simulation
                    next_t = time.monotonic()
                next_t += period
                time.sleep(max(0.0, next_t - time.monotonic()))
            assert isinstance(rig.cell, SimulatedCell)
            history = rig.cell.joint_torque_history()
    except DriveError as exc:  # a drive that stopped answering ends the measurement
        print(f"stopped: {exc}")
        return
    # the last rows are this loop's SYNCs (enable may have sent some before it)
    sim_s = history.time_s[-len(sync_ns) :]
    lag = sim_s - np.array(sync_ns) * 1e-9
    lag -= np.median(lag)
    size = np.abs(lag) * 1e6
    apart = (np.median(lag[pause_at + 1 :]) - np.median(lag[: pause_at + 1])) * 1e6
    print(
        f"|simulated − wall| about the median: p50 {np.quantile(size, 0.5):.0f} µs, p99 "
        f"{np.quantile(size, 0.99):.0f} µs, max {size.max():.0f} µs; over {size.size} SYNCs"
    )
    print(
        f"across the pause the clocks moved apart by {apart:+.0f} µs (a simulation that "
        f"stopped with the master would show {-pause_s * 1e6:+.0f} µs)"
    )


def lockstep_against_baseline(ref: str, repeats: int, folder: Path) -> None:
    """``drivegain acquire`` in lockstep (shipped simulated TX-40 and trajectory), whole
    processes of this tree beside REF installed in a temporary venv (benchmarks/baseline.py)."""
    from baseline import (
        BaselineInstall,
        best_of,
        comparison_header,
        comparison_line,
        current_command,
    )

    from drivegain.config import resource_path

    args = [
        "acquire",
        "--config",
        str(resource_path("acquire-sim.toml")),
        "--trajectory",
        str(resource_path("tx40-excitation.json")),
    ]
    print(f"\nlockstep acquire, this tree beside {ref} (installing it offline)...", flush=True)
    with BaselineInstall(ref) as base:
        print(f"  done in {base.install_s:.0f} s: {base.check()}")
        print(f"best of {repeats}, interleaved; ratio = baseline / now")
        print(comparison_header())
        # a log is never overwritten: every run writes a file of its own
        runs = [
            best_of(
                [
                    [*current_command("drivegain"), *args, "--out", str(folder / f"now-{r}.mcap")],
                    [*base.command("drivegain"), *args, "--out", str(folder / f"base-{r}.mcap")],
                ],
                1,
            )
            for r in range(repeats)
        ]
        now = min((r[0] for r in runs), key=lambda m: m.wall_s)
        then = min((r[1] for r in runs), key=lambda m: m.wall_s)
        print(comparison_line("acquire, lockstep, shipped trajectory", now, then), flush=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--duration", type=float, default=60.0, help="realtime excitation seconds")
    p.add_argument("--rates", type=float, nargs="+", default=[250.0, 400.0], help="Hz")
    p.add_argument("--lockstep-seconds", type=float, default=60.0)
    p.add_argument("--memory-minutes", type=float, default=10.0)
    p.add_argument("--simclock-cycles", type=int, default=1000, help="simulated-clock SYNCs")
    p.add_argument(
        "--skip",
        nargs="*",
        default=[],
        choices=["realtime", "lockstep", "memory", "simclock"],
    )
    p.add_argument(
        "--sim-host",
        choices=["process", "thread"],
        default="process",
        help="realtime: simulated drives in their own process (default) or the master's",
    )
    p.add_argument(
        "--rt-priority", type=int, default=80, help="realtime: SCHED_FIFO priority, 0 = off"
    )
    p.add_argument(
        "--spin-s",
        type=float,
        default=0.0,
        help="realtime: [acquisition] spin_s of the sessions (busy-waited end of each period, s)",
    )
    p.add_argument(
        "--switch-interval-s",
        type=float,
        default=None,
        help="realtime: the interpreter's switch interval of the rigs, s (default: left at "
        "Python's 0.005; docs/realtime.md)",
    )
    p.add_argument(
        "--same-cycle",
        action="store_true",
        help="realtime: also run the same-cycle master (waits for each cycle's own TPDOs)",
    )
    p.add_argument(
        "--baseline-ref",
        nargs="?",
        const="c03ea6b",
        metavar="REF",
        help="instead: the whole lockstep acquire command beside REF's (default c03ea6b)",
    )
    p.add_argument("--repeats", type=int, default=1, help="--baseline-ref: runs of each")
    args = p.parse_args(argv)
    global _SWITCH_INTERVAL_S
    _SWITCH_INTERVAL_S = args.switch_interval_s
    quiet_libraries()
    with tempfile.TemporaryDirectory(prefix="bench-acquire-") as tmp:
        folder = Path(tmp)
        if args.baseline_ref:
            lockstep_against_baseline(args.baseline_ref, args.repeats, folder)
            return 0
        if "realtime" not in args.skip:
            realtime(
                args.duration,
                args.rates,
                folder,
                args.sim_host,
                args.rt_priority,
                same_cycle=args.same_cycle,
                spin_s=args.spin_s,
            )
        if "lockstep" not in args.skip:
            lockstep(args.lockstep_seconds, folder)
        if "memory" not in args.skip:
            memory(args.memory_minutes, folder)
        if "simclock" not in args.skip:
            simulated_clock(args.simclock_cycles, folder)
    return 0


if __name__ == "__main__":
    sys.exit(main())
