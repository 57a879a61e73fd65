"""The rig's realtime policy: the freeze from open to close, SCHED_FIFO on a session's cycle
thread and its restoration, a refusal recorded in the log, the interpreter's switch interval."""

from __future__ import annotations

import errno
import gc
import os
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from drivegain.acquire.config import load_acquisition_config
from drivegain.acquire.request import RunRequest, prepare_run
from drivegain.acquire.rig import Rig, realtime_policy
from drivegain.acquire.session import RunResult, RunState, Session
from drivegain.drivers import gcfreeze
from drivegain.drivers.realtime import RealtimePolicy
from drivegain.drivers.simprocess import SimulatedCellProcess
from drivegain.errors import ConfigError
from drivegain.formats.log import EventLevel
from drivegain.formats.logreader import read_run


def test_the_policy_of_a_configuration(make_config: Callable[..., Path]) -> None:
    lockstep = load_acquisition_config(make_config(acquisition="rt_priority = 80"))
    realtime = load_acquisition_config(
        make_config(clock="realtime", acquisition="rt_priority = 80")
    )
    # a lockstep cycle has no deadline: no SCHED_FIFO, but the freeze all the same; the switch
    # interval is left as it is in both
    assert realtime_policy(lockstep) == RealtimePolicy(gc_freeze=True, fifo_priority=0)
    assert realtime_policy(realtime) == RealtimePolicy(gc_freeze=True, fifo_priority=80)


def test_the_switch_interval_is_set_in_the_block_and_restored_after_nesting() -> None:
    before = sys.getswitchinterval()
    with RealtimePolicy(gc_freeze=False, switch_interval_s=0.0005).process():
        assert sys.getswitchinterval() == pytest.approx(0.0005)
        with RealtimePolicy(gc_freeze=False, switch_interval_s=0.002).process():
            assert sys.getswitchinterval() == pytest.approx(0.002)
        assert sys.getswitchinterval() == pytest.approx(0.0005)
        with RealtimePolicy(gc_freeze=False).process():  # None: left as it is
            assert sys.getswitchinterval() == pytest.approx(0.0005)
    assert sys.getswitchinterval() == before
    with (
        pytest.raises(RuntimeError),
        RealtimePolicy(gc_freeze=False, switch_interval_s=0.001).process(),
    ):
        raise RuntimeError("the block fails")
    assert sys.getswitchinterval() == before


@pytest.mark.parametrize("bad", [0.0, -1e-3, 2.0])
def test_a_switch_interval_out_of_range_is_refused(bad: float) -> None:
    with pytest.raises(ConfigError, match="switch interval"):
        RealtimePolicy(switch_interval_s=bad)


def test_a_rig_holds_the_freeze_from_open_to_close(make_config: Callable[..., Path]) -> None:
    base = gcfreeze.holders()
    rig = Rig(load_acquisition_config(make_config()))
    rig.open()
    try:
        assert gcfreeze.holders() > base and gc.get_freeze_count() > 0
    finally:
        rig.close()
    assert gcfreeze.holders() == base
    rig.close()  # again: nothing left to release
    assert gcfreeze.holders() == base


def _run_on_a_thread(
    make_config: Callable[..., Path], trajectory: Path, out: Path, policy: RealtimePolicy
) -> tuple[RunResult, list[tuple[int, int]], tuple[int, int], tuple[int, int]]:
    """A lockstep session with ``policy`` on a fresh thread; the thread's scheduling before,
    during (first cycle) and after the run."""
    cfg = load_acquisition_config(make_config())
    prepared = prepare_run(cfg, RunRequest(trajectory, out))
    during: list[tuple[int, int]] = []
    out_: dict[str, Any] = {}

    def scheduling() -> tuple[int, int]:
        return os.sched_getscheduler(0), os.sched_getparam(0).sched_priority

    def on_cycle(s: Session) -> None:
        if not during:
            during.append(scheduling())

    def target() -> None:
        try:
            out_["before"] = scheduling()
            out_["result"] = session.run()
        except BaseException as exc:
            out_["error"] = exc
        finally:
            out_["after"] = scheduling()

    with Rig(cfg, policy=policy) as master:
        session = Session(cfg, master, prepared, on_cycle=on_cycle, policy=policy)
        session.plan()
        th = threading.Thread(target=target, name="drivegain-cycle-test")
        th.start()
        th.join(120)
    if "error" in out_:
        raise out_["error"]
    return out_["result"], during, out_["before"], out_["after"]


def test_the_cycle_thread_runs_at_the_policy_and_goes_back_after(
    tmp_path: Path, make_config: Callable[..., Path], short_trajectory: Path
) -> None:
    probe: dict[str, bool] = {}
    th = threading.Thread(target=lambda: probe.update(ok=_fifo_allowed()))
    th.start()
    th.join()
    if not probe["ok"]:
        pytest.skip("SCHED_FIFO is refused here")
    res, during, before, after = _run_on_a_thread(
        make_config, short_trajectory, tmp_path / "run.mcap", RealtimePolicy(fifo_priority=3)
    )
    assert res.state is RunState.FINISHED
    assert during == [(os.SCHED_FIFO, 3)]
    assert after == before and before[0] != os.SCHED_FIFO
    assert not any("SCHED_FIFO" in e["text"] for e in read_run(res.path).events)


def test_a_refused_priority_is_a_warning_in_the_log_and_the_run_goes_on(
    tmp_path: Path,
    make_config: Callable[..., Path],
    short_trajectory: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def refuse(pid: int, policy: int, param: os.sched_param) -> None:
        raise PermissionError(errno.EPERM, os.strerror(errno.EPERM))

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    res, during, before, after = _run_on_a_thread(
        make_config, short_trajectory, tmp_path / "run.mcap", RealtimePolicy(fifo_priority=80)
    )
    assert res.state is RunState.FINISHED and during == [before] and after == before
    log = read_run(res.path)
    warnings = [e for e in log.events if "SCHED_FIFO" in e["text"]]
    assert len(warnings) == 1 and warnings[0]["level"] == EventLevel.WARNING
    assert "priority 80" in warnings[0]["text"] and "normal priority" in warnings[0]["text"]
    assert log.events[-1]["text"] == f"run finished: {res.cycles} cycles"


def _fifo_allowed() -> bool:
    with RealtimePolicy(fifo_priority=1).cycle_thread() as fifo:
        return fifo.granted


def test_drives_in_a_child_process_get_the_rigs_policy(make_config: Callable[..., Path]) -> None:
    cfg = load_acquisition_config(make_config(interface="drivegain-ipc"))
    policy = RealtimePolicy(cpus=frozenset({min(os.sched_getaffinity(0))}))
    rig = Rig(cfg, policy=policy)
    rig.open()
    try:
        assert isinstance(rig.cell, SimulatedCellProcess) and rig.cell.policy == policy
        assert rig.cell.pid is not None and os.sched_getaffinity(rig.cell.pid) == policy.cpus
    finally:
        rig.close()
