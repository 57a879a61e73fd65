"""Run checks are bounded: explicit limits on a run's size, one period of the periodic
excitation checked whatever the number of periods, signals honoured during the checks, and a log
that cannot be started (full disk) is one line that leaves nothing behind."""

from __future__ import annotations

import dataclasses
import errno
import json
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivegain.acquire.checks import SAMPLE_BUDGET, check_motion
from drivegain.acquire.config import load_acquisition_config
from drivegain.acquire.request import (
    MAX_EXCITATION_S,
    MAX_HARMONICS,
    MAX_PERIODS,
    RunRequest,
    prepare_run,
)
from drivegain.config import load_robot, resource_path
from drivegain.errors import DataError, InputError, TrajectoryError
from drivegain.excite.limits import USAGE_BUDGET, ExcitationLimits, fourier_usage
from drivegain.excite.motion import Motion, plan_motion
from drivegain.formats.fourier import FourierTrajectory

ROBOT = load_robot(resource_path("tx40.toml"))


def _variant(src: Path, dst: Path, **changes: Any) -> Path:
    doc = json.loads(src.read_text())
    for key, value in changes.items():
        if key == "base_frequency_hz":
            doc["fourier"][key] = value
        elif key == "harmonics":
            for name in ("a", "b"):
                doc["fourier"][name] = [
                    row + [0.0] * (value - len(row)) for row in doc["fourier"][name]
                ]
            doc["fourier"].pop("harmonics", None)
        else:
            doc[key] = value
    dst.write_text(json.dumps(doc))
    return dst


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            {"periods": 1_000_000_000},
            f"key 'periods': 1000000000 periods: a run has at most {MAX_PERIODS}",
        ),
        (
            {"periods": 400, "base_frequency_hz": 0.1},
            f"400 periods of 10 s make 4000 s of excitation: a run lasts at most "
            f"{MAX_EXCITATION_S:g} s",
        ),
        ({"harmonics": MAX_HARMONICS + 1}, f"key 'fourier.a': {MAX_HARMONICS + 1} harmonics"),
    ],
)
def test_a_run_past_the_explicit_limits_is_refused_before_any_check(
    tmp_path: Path,
    make_config: Callable[..., Path],
    short_trajectory: Path,
    change: dict[str, Any],
    message: str,
) -> None:
    cfg = load_acquisition_config(make_config())
    traj = _variant(short_trajectory, tmp_path / "t.json", **change)
    t0 = time.monotonic()
    with pytest.raises(DataError) as e:
        prepare_run(cfg, RunRequest(traj, tmp_path / "r.mcap"))
    assert time.monotonic() - t0 < 10.0  # generous: the unbounded check took minutes
    assert str(e.value).startswith(f"{traj}: ") and message in str(e.value), str(e.value)
    assert not list(tmp_path.glob("r.mcap*"))


def test_a_long_run_within_the_limits_is_accepted(
    tmp_path: Path, make_config: Callable[..., Path], short_trajectory: Path
) -> None:
    cfg = load_acquisition_config(make_config())
    traj = _variant(short_trajectory, tmp_path / "t.json", periods=1500 // 2)  # 1500 s
    prepared = prepare_run(cfg, RunRequest(traj, tmp_path / "r.mcap"))
    assert prepared.excitation.fourier.duration_s == pytest.approx(1500.0)


def _count_samples(motion: Motion) -> list[int]:
    counts: list[int] = []
    original = motion.sample

    def counting(t: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        counts.append(int(np.size(t)))
        return original(t)

    motion.sample = counting
    return counts


def _series(periods: int, base_hz: float = 0.5) -> FourierTrajectory:
    rng = np.random.default_rng(0)
    q0 = np.array([0.1, -0.2, 0.3, 0.0, 0.4, 0.0])
    a, b = rng.uniform(-0.3, 0.3, (2, ROBOT.n, 2))
    return FourierTrajectory(base_hz, q0, a, b, periods)


def test_the_motion_check_looks_at_one_period_whatever_the_number_of_periods() -> None:
    """1000 periods of 2 s (2000 s, 500 000 cycles at 4 ms): the check samples the approach,
    one period and the retreat, about as many cycles as a one-period motion."""
    period_s = 0.004
    short = plan_motion(ROBOT, _series(1), np.zeros(ROBOT.n))
    long = plan_motion(ROBOT, _series(1000), np.zeros(ROBOT.n))
    counts_short, counts_long = _count_samples(short), _count_samples(long)
    check_motion(ROBOT, short, period_s)
    check_motion(ROBOT, long, period_s)
    one_period_motion = short.duration_s / period_s
    assert sum(counts_long) < 1.2 * one_period_motion + 100, (sum(counts_long), one_period_motion)
    assert sum(counts_short) < 1.2 * one_period_motion + 100
    assert long.duration_s / period_s > 100 * sum(counts_long)


def test_the_bounded_motion_check_still_finds_a_violation() -> None:
    """Limits lowered under the motion's speeds: the approach, the excitation's first period and
    the retreat are each still checked."""
    motion = plan_motion(ROBOT, _series(500), np.zeros(ROBOT.n))
    _, qd, _ = motion.sample(np.arange(0.0, motion.duration_s, 0.01)[:2000])
    slow = np.abs(qd).max(axis=0) * 0.5
    joints = tuple(
        dataclasses.replace(j, velocity_limit=float(v))
        for j, v in zip(ROBOT.joints, slow, strict=True)
    )
    robot = dataclasses.replace(ROBOT, joints=joints)
    with pytest.raises(TrajectoryError, match=r"motion: j\d: velocity .* exceeds the limit"):
        check_motion(robot, motion, 0.004)


def test_the_rigorous_excitation_bound_has_bounded_work() -> None:
    """A 1000 s period (0.001 Hz, the lowest excite allows) with 50 harmonics: the 1 ms grid
    would be 1 000 000 points x 101 columns (800 MB per derivative); the grid is coarsened to
    the budget and the bound stays rigorous (at least the sampled maximum)."""
    rng = np.random.default_rng(1)
    h = 50
    f = FourierTrajectory(0.001, np.zeros(ROBOT.n), rng.normal(size=(ROBOT.n, h)) * 1e-4,
                          rng.normal(size=(ROBOT.n, h)) * 1e-4)  # fmt: skip
    lim = ExcitationLimits.from_robot(ROBOT, 0.0, 1.0)
    usage = fourier_usage(f, lim)
    assert usage.dt >= f.period_s / (USAGE_BUDGET // (1 + 2 * h)) * 0.999
    t = np.linspace(0.0, f.period_s, 20_001)
    _, qd, _, _ = f.evaluate(t)
    assert np.all(usage.usage[1] >= np.abs(qd).max(axis=0) / lim.symmetric(1) - 1e-12)
    assert SAMPLE_BUDGET > 0


# -- signals during the checks, and a log that cannot be started --------------------------------

_SLOW_CHECKS = """
import sys, time
import drivegain.acquire.request as request

def slow(*args, **kw):
    print("CHECKING", file=sys.stderr, flush=True)
    time.sleep(60)

request.check_excitation = slow
from drivegain.cli import main
raise SystemExit(main(sys.argv[1:]))
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_long_checks_is_honoured_at_once(
    tmp_path: Path, make_config: Callable[..., Path], short_trajectory: Path, sig: signal.Signals
) -> None:
    """`drivegain acquire` ignored SIGINT/SIGTERM for 10 minutes in its checks; now the checks
    run on a worker the command abandons: it stops within a second, nothing written."""
    out = tmp_path / "r.mcap"
    cmd = [sys.executable, "-c", _SLOW_CHECKS, "acquire", "--config", str(make_config())]
    cmd += ["--trajectory", str(short_trajectory), "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert proc.stderr is not None
        seen = b""
        while b"CHECKING" not in seen:
            line = proc.stderr.readline()
            assert line, proc.communicate()
            seen += line
        t0 = time.monotonic()
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
        elapsed = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert elapsed < 5.0, elapsed  # one second, with room for a busy machine
    text = err.decode()
    assert proc.returncode == 0 and "during the checks, before any motion" in text, text
    assert "Traceback" not in text
    assert not list(tmp_path.glob("r.mcap*"))


def test_a_full_disk_before_the_run_is_one_line_and_no_part_is_left(
    tmp_path: Path,
    make_config: Callable[..., Path],
    short_trajectory: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """ENOSPC when the log is started (its header is written after the .part is created): one
    line naming the file, exit 2, no .part; the retry on a disk with room then runs."""
    from drivegain.cli import main
    from drivegain.formats.logwriter import LogWriter

    def full(self: LogWriter) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    out = tmp_path / "r.mcap"
    cfg = make_config()
    args = ["acquire", "--config", str(cfg), "--trajectory", str(short_trajectory)]
    args += ["--out", str(out)]
    with monkeypatch.context() as m:
        m.setattr(LogWriter, "flush", full)
        status = main(args)
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2, err
    assert err[-1].startswith(f"drivegain: error: {out}.part: cannot write the log (No space")
    assert "internal error" not in "\n".join(err)
    assert not list(tmp_path.glob("r.mcap*"))
    assert main(args) == 0  # the retry is not blocked
    assert out.exists() and not list(tmp_path.glob("*.part"))
    with pytest.raises(InputError):  # and a log is still never overwritten
        prepare_run(load_acquisition_config(cfg), RunRequest(short_trajectory, out))
