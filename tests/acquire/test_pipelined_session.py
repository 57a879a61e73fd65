"""A pipelined session (realtime's cycle) logs what a same-cycle session logs.

Both run on the deterministic lockstep cell here, so the drives' answers do not depend on when
the master collects them: the pipelined loop, which records cycle k−1 after sending SYNC k, must
log the same positions, currents and setpoints against the same ``cycle`` and ``t``, down to the
last cycle (collected after the last SYNC). Supervision of a pipelined run still quick-stops with
the cycle that shows the fault in the log.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from drivegain.acquire.config import load_acquisition_config
from drivegain.acquire.request import RunRequest, prepare_run
from drivegain.acquire.rig import Rig
from drivegain.acquire.session import RunResult, RunState, Session
from drivegain.acquire.supervision import SupervisionFault
from drivegain.formats.log import EventLevel
from drivegain.formats.logreader import read_run


def _run(
    config: Path, trajectory: Path, out: Path, *, pipelined: bool
) -> tuple[Session, RunResult]:
    cfg = load_acquisition_config(config)
    prepared = prepare_run(cfg, RunRequest(trajectory, out))
    with Rig(cfg) as master:
        session = Session(cfg, master, prepared, pipelined=pipelined)
        session.plan()
        try:
            return session, session.run()
        except SupervisionFault:
            assert session.result is not None
            return session, session.result


def test_a_pipelined_log_equals_the_same_cycle_log(
    tmp_path: Path, make_config: Callable[..., Path], short_trajectory: Path
) -> None:
    config = make_config()
    same, res_same = _run(config, short_trajectory, tmp_path / "same.mcap", pipelined=False)
    piped, res_piped = _run(config, short_trajectory, tmp_path / "piped.mcap", pipelined=True)
    assert not same.pipelined and piped.pipelined
    assert piped.master.layout.tagged  # so the pipelined run staged its RPDOs (Master.stage)
    assert res_same.state is res_piped.state is RunState.FINISHED
    assert res_piped.cycles == res_same.cycles
    a, b = read_run(res_same.path), read_run(res_piped.path)  # type: ignore[arg-type]
    np.testing.assert_array_equal(b.cycle, np.arange(res_piped.cycles))
    np.testing.assert_array_equal(b.cycle, a.cycle)
    np.testing.assert_array_equal(b.t, a.t)
    for name in ("position", "current", "current_reference", "setpoint"):
        np.testing.assert_array_equal(getattr(b, name), getattr(a, name), err_msg=name)
    assert b.events[-1]["text"] == f"run finished: {res_piped.cycles} cycles"
    assert piped.held_cycles == 0 and same.held_cycles == 0


def test_a_pipelined_supervision_fault_is_logged_with_its_cycle(
    tmp_path: Path, make_config: Callable[..., Path], short_trajectory: Path
) -> None:
    """The following error is seen one call later, but on the cycle whose positions show it:
    that cycle is the last one logged, the fault names it, and the drives are quick-stopped."""
    config = make_config(acquisition="following_error = 0.002")
    _, res = _run(config, short_trajectory, tmp_path / "fe.mcap", pipelined=True)
    assert res.state is RunState.FAULT and res.fault is not None
    assert "following error" in res.fault
    log = read_run(res.path)  # type: ignore[arg-type]
    last = int(log.cycle[-1])
    assert f"at cycle {last}" in res.fault
    np.testing.assert_array_equal(log.cycle, np.arange(last + 1))
    fault = log.events[-1]
    assert fault["level"] == EventLevel.ERROR and fault["action"] == "quick stop"


@pytest.mark.parametrize("pipelined", [True, False])
def test_the_default_is_pipelined_in_realtime_only(
    make_config: Callable[..., Path], short_trajectory: Path, tmp_path: Path, pipelined: bool
) -> None:
    clock = "realtime" if pipelined else "lockstep"
    cfg = load_acquisition_config(make_config(clock=clock))
    prepared = prepare_run(cfg, RunRequest(short_trajectory, tmp_path / "x.mcap"))
    session = Session(cfg, master=None, prepared=prepared)  # type: ignore[arg-type]
    assert session.pipelined is pipelined
