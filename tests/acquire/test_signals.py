"""``drivegain acquire`` in a subprocess: SIGTERM stops safely, SIGKILL leaves a readable .part."""

from __future__ import annotations

import signal
from collections.abc import Callable
from pathlib import Path
from subprocess import Popen
from types import SimpleNamespace

import numpy as np
import pytest

from drivegain.config import load_robot, resource_path
from drivegain.excite.trajectory import load_trajectory
from drivegain.formats.logreader import read_run


def test_sigterm_stops_safely_and_finishes_the_log(
    long_run: Callable[..., tuple[Popen[bytes], int, Path]],
    make_config: Callable[..., Path],
    long_trajectory: Path,
    acquire_cli: SimpleNamespace,
) -> None:
    cfg = make_config(acquisition="flush_interval_s = 0.2")
    proc, _, out = long_run(cfg, 600)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err.decode()
    assert b"stopped" in err
    assert out.exists() and not out.with_name("run.mcap.part").exists()
    log = read_run(out)
    assert not log.truncated and np.all(np.diff(log.cycle) == 1) and log.cycle[0] == 0
    assert log.events[-1]["text"].startswith("operator stop (SIGTERM): robot at rest")
    # stopped during the excitation, well before its planned end
    planned = load_trajectory(long_trajectory).fourier.duration_s / log.sync_period_s
    assert log.cycle[-1] < planned
    robot = load_robot(resource_path("tx40.toml"))
    v = np.diff(log.setpoint, axis=0) / log.sync_period_s
    a = np.diff(v, axis=0) / log.sync_period_s
    assert np.all(np.abs(a) <= robot.acceleration_limits * 1.01)
    np.testing.assert_allclose(v[-20:], 0.0, atol=1e-9)
    acquire_cli.assert_at_rest(log.position, log.sync_period_s)  # the robot itself
    with pytest.raises(AssertionError, match="still moving"):  # and the check tells motion
        acquire_cli.assert_at_rest(log.position[:300], log.sync_period_s)


def test_sigkill_leaves_a_part_with_every_flushed_cycle(
    long_run: Callable[..., tuple[Popen[bytes], int, Path]], make_config: Callable[..., Path]
) -> None:
    cfg = make_config(acquisition="flush_interval_s = 0.2")
    proc, seen, out = long_run(cfg, 500)
    part = out.with_name("run.mcap.part")
    proc.kill()
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    assert part.exists() and not out.exists()
    log = read_run(part)
    assert log.truncated and log.messages_recovered >= seen
    np.testing.assert_array_equal(log.cycle, np.arange(log.cycle.size))
    assert log.meta["run"] == "unloaded" and "tx40.toml" in log.attachments
