"""Cycle pacing (absolute deadlines, overruns), jitter statistics and per-cycle supervision."""

from __future__ import annotations

import numpy as np
import pytest

from drivegain.acquire import pacing
from drivegain.acquire.pacing import LockstepPacer, RealtimePacer
from drivegain.acquire.stats import Histogram, LoopStats
from drivegain.acquire.supervision import Supervision, SupervisionFault, Supervisor
from drivegain.config import load_robot, resource_path


class FakeClock:
    """Monotonic and wall clocks that only move when slept on or told to."""

    def __init__(self) -> None:
        self.mono = 10_000_000_000
        self.sleeps: list[float] = []

    def monotonic_ns(self) -> int:
        return self.mono

    def time_ns(self) -> int:
        return self.mono + 1_700_000_000_000_000_000

    def sleep(self, s: float) -> None:
        self.sleeps.append(s)
        self.mono += round(s * 1e9) + 30_000  # every sleep oversleeps by 30 µs


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> FakeClock:
    c = FakeClock()
    monkeypatch.setattr(pacing.time, "monotonic_ns", c.monotonic_ns)
    monkeypatch.setattr(pacing.time, "time_ns", c.time_ns)
    monkeypatch.setattr(pacing.time, "sleep", c.sleep)
    return c


def test_realtime_deadlines_are_absolute(clock: FakeClock) -> None:
    stats = LoopStats(period_s=0.004, clock="realtime")
    p = RealtimePacer(0.004, stats)
    p.start()
    t0 = clock.mono
    for k in range(100):
        p.wait(k)
        clock.mono += 1_500_000  # the cycle's work: 1.5 ms
    # the 30 µs oversleep of each cycle does not accumulate: cycle 99 woke 30 µs after t0 + 100 T
    assert p.deadline_ns(99) == t0 + 100 * 4_000_000
    assert stats.overruns == 0
    assert stats.wake_late.count == 100
    assert stats.wake_late.quantile(0.99) == pytest.approx(30_000, abs=1_000)


def test_the_time_the_drives_take_to_enable_does_not_make_cycle_0_late(clock: FakeClock) -> None:
    """The session starts its pacer, enables the drives (tens of ms of SDO exchanges), then
    anchors the deadlines: cycle 0 is due a period after the anchor, not after the start."""
    stats = LoopStats(period_s=0.004, clock="realtime")
    p = RealtimePacer(0.004, stats)
    p.start()
    clock.mono += 15_000_000  # enabling: 15 ms
    p.anchor()
    anchored = clock.mono
    p.wait(0)
    assert p.deadline_ns(0) == anchored + 4_000_000
    assert stats.overruns == 0 and stats.wake_late.quantile(1.0) == pytest.approx(30_000, abs=1)


def test_a_spinning_pacer_sleeps_short_and_busy_waits_to_the_deadline(
    clock: FakeClock, monkeypatch: pytest.MonkeyPatch
) -> None:
    """spin_s = 0.3 ms: the sleep ends 0.3 ms early (its 30 µs oversleep included), the rest is
    busy-waited, so the cycle starts at its deadline, not 30 µs after it."""
    reads = 0

    def ticking() -> int:  # busy-waiting reads the clock; each read takes 1 µs here
        nonlocal reads
        reads += 1
        clock.mono += 1_000
        return clock.mono

    monkeypatch.setattr(pacing.time, "monotonic_ns", ticking)
    stats = LoopStats(period_s=0.004, clock="realtime")
    p = RealtimePacer(0.004, stats, spin_s=3e-4)
    p.start()
    deadline = p.deadline_ns(0)
    p.wait(0)
    assert clock.sleeps[0] == pytest.approx(0.004 - 3e-4, abs=5e-6)
    assert reads > 200  # spun
    assert 0 <= stats.wake_late.quantile(1.0) <= 2_000 and clock.mono - deadline <= 3_000


def test_realtime_overrun_reanchors_without_a_burst(clock: FakeClock) -> None:
    stats = LoopStats(period_s=0.004, clock="realtime")
    p = RealtimePacer(0.004, stats)
    p.start()
    p.wait(0)
    clock.mono += 13_000_000  # a 13 ms stall: three deadlines missed
    p.wait(1)
    assert stats.overruns == 1 and p.consecutive_overruns == 1
    woke = clock.mono
    clock.mono += 100_000
    p.wait(2)
    # the next SYNC is one period after the re-anchored deadline, not immediately
    assert clock.mono - woke >= 4_000_000 - 1_000_000
    assert p.consecutive_overruns == 0


def test_a_late_cycle_moves_the_schedule_rather_than_shortening_the_next(
    clock: FakeClock,
) -> None:
    """2 ms late (less than a period, more than a quarter of one): not an overrun, but the next
    SYNC still comes a full period later. Under the absolute schedule it would come after 2 ms,
    and the drives, each reaching its target a period after its SYNC, would fall behind, then
    catch up faster than the trajectory."""
    stats = LoopStats(period_s=0.004, clock="realtime")
    p = RealtimePacer(0.004, stats)
    p.start()
    p.wait(0)
    clock.mono += 6_000_000  # the cycle's work took 6 ms
    p.wait(1)
    woke = clock.mono
    assert stats.overruns == 0
    clock.mono += 1_000_000
    p.wait(2)
    assert clock.mono - woke == pytest.approx(4_000_000, abs=100_000)
    assert stats.wake_late.quantile(1.0) == pytest.approx(2_000_000, rel=0.05)


def test_a_sync_sent_late_after_an_on_time_wake_up_moves_the_schedule(clock: FakeClock) -> None:
    """The delay can come after the wake-up (a stall while the RPDOs go out): what counts is
    when the SYNC itself was sent."""
    stats = LoopStats(period_s=0.004, clock="realtime")
    p = RealtimePacer(0.004, stats)
    p.start()
    p.wait(0)
    clock.mono += 500_000
    p.wait(1)  # on time
    clock.mono += 1_500_000  # the SYNC goes out 1.5 ms after the deadline
    sent = clock.mono
    p.sync_sent(1, sent)
    p.wait(2)
    assert clock.mono - sent == pytest.approx(4_000_000, abs=100_000)
    # a SYNC only a little late leaves the schedule alone
    p.sync_sent(2, clock.mono + 200_000)
    assert p.deadline_ns(3) == p.deadline_ns(2) + 4_000_000
    assert p.deadline_ns(2) == sent + 4_000_000


def test_lockstep_log_times_are_simulated() -> None:
    stats = LoopStats(period_s=0.002, clock="lockstep")
    p = LockstepPacer(0.002, stats)
    p.start()
    times = [p.wait(k) for k in range(5)]
    assert np.all(np.diff(times) == 2_000_000)


def test_histogram_quantiles_match_numpy() -> None:
    rng = np.random.default_rng(3)
    values = rng.gamma(2.0, 50_000.0, size=20_000).astype(int)
    h = Histogram()
    for v in values:
        h.add(int(v))
    for q in (0.5, 0.9, 0.99):
        assert h.quantile(q) == pytest.approx(np.quantile(values, q), abs=1_500)
    assert h.max_ns == values.max()
    huge = Histogram(max_ns=1_000_000)
    huge.add(5_000_000)
    assert huge.quantile(0.99) == 5_000_000


@pytest.fixture(scope="module")
def robot():  # type: ignore[no-untyped-def]
    return load_robot(resource_path("tx40.toml"))


def _supervisor(robot, fe: float = 0.05) -> Supervisor:  # type: ignore[no-untyped-def]
    return Supervisor(robot, Supervision(following_error=np.full(robot.n, fe)), 0.004)


def test_supervision_passes_normal_tracking(robot) -> None:  # type: ignore[no-untyped-def]
    s = _supervisor(robot)
    t = np.arange(500) * 0.004
    sp = 0.3 * np.sin(np.outer(t, np.ones(6)))
    for k in range(500):
        # the drive lags one cycle plus a little tracking error
        pos = sp[max(k - 1, 0)] + 1e-4
        s.check(k, pos, sp[k])
    assert np.all(s.max_following_error < 1e-3)


def test_supervision_following_error_names_the_joint(robot) -> None:  # type: ignore[no-untyped-def]
    s = _supervisor(robot)
    q = np.zeros(6)
    s.check(0, q, q)
    bad = q.copy()
    bad[3] = 0.06
    with pytest.raises(SupervisionFault, match=r"j4: following error 0\.0600") as e:
        s.check(1, bad, q)
    assert e.value.node == 4


def test_supervision_position_limit_and_speed(robot) -> None:  # type: ignore[no-untyped-def]
    s = _supervisor(robot, fe=10.0)
    q = np.zeros(6)
    q[1] = robot.upper[1] + 0.03
    with pytest.raises(SupervisionFault, match=r"j2: position .* beyond limit") as e:
        s.check(0, q, q)
    assert e.value.node == 2
    s = _supervisor(robot, fe=10.0)
    s.check(0, np.zeros(6), np.zeros(6))
    fast = np.zeros(6)
    fast[5] = 0.1  # 25 rad/s over 4 ms, above 1.25 x 12.2 rad/s
    with pytest.raises(SupervisionFault, match="j6: speed"):
        s.check(1, fast, fast)
    s = _supervisor(robot)
    nan = np.zeros(6)
    nan[0] = np.nan
    with pytest.raises(SupervisionFault, match="j1: non-finite"):
        s.check(0, nan, np.zeros(6))
