"""Helpers of the acquire tests: short trajectories, simulated-cell configs, in-process daemons,
leak checks."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from drivegain.acquire.config import AcquisitionConfig, load_acquisition_config
from drivegain.acquire.daemon import Daemon
from drivegain.config import load_robot, resource_path
from drivegain.excite.trajectory import save_trajectory, trajectory_document
from drivegain.formats.fourier import FourierTrajectory
from drivegain.formats.logreader import iter_channel

_channels = itertools.count()


def write_trajectory(
    path: Path, *, base_hz: float = 0.5, periods: int = 1, scale: float = 0.3, seed: int = 0
) -> Path:
    """A small smooth Fourier excitation (2 harmonics) of the TX-40, well inside its limits."""
    robot = load_robot(resource_path("tx40.toml"))
    rng = np.random.default_rng(seed)
    a = rng.uniform(-scale, scale, (robot.n, 2))
    b = rng.uniform(-scale, scale, (robot.n, 2))
    q0 = np.array([0.1, -0.2, 0.3, 0.0, 0.4, 0.0])
    f = FourierTrajectory(base_hz, q0, a, b, periods)
    return save_trajectory(path, trajectory_document(f, robot, {"cond": 0.0}))


def write_config(
    path: Path,
    *,
    clock: str = "lockstep",
    period_s: float = 0.004,
    faults: list[dict[str, Any]] = (),  # type: ignore[assignment]
    acquisition: str = "",
    daemon: str = "",
    bitrate: int = 1_000_000,
    noise: float = 0.05,
    interface: str = "virtual",
) -> Path:
    """An acquisition TOML of the simulated TX-40 on its own channel.

    ``interface = "drivegain-ipc"`` puts the simulated drives in a child process; the channel is
    then a socket path (short: Unix socket paths are limited to about 100 bytes).
    """
    channel = f"acq-test-{next(_channels)}-{time.monotonic_ns()}"
    if interface != "virtual":
        channel = f"/tmp/dg-{channel}.sock"
    lines = [
        "[acquisition]",
        f'robot = "{resource_path("tx40.toml")}"',
        f"period_s = {period_s}",
        acquisition,
        "[bus]",
        f'interface = "{interface}"',
        f'channel = "{channel}"',
        f"bitrate = {bitrate}",
        "[simulation]",
        f'clock = "{clock}"',
        "seed = 3",
        f"current_noise_nm = {noise}",
        "history_s = 30.0",
    ]
    for f in faults:
        lines.append("[[simulation.fault]]")
        lines.extend(f"{k} = {json.dumps(v)}" for k, v in f.items())
    if daemon:
        lines += ["[daemon]", daemon]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="session")
def short_trajectory(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """About 3 s of motion: approach, one 2 s period at 0.5 Hz, retreat."""
    return write_trajectory(tmp_path_factory.mktemp("traj") / "short.json")


@pytest.fixture(scope="session")
def long_trajectory(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """About 80 s of motion (40 periods at 0.5 Hz, 20 000 cycles at 4 ms), for runs that a test
    stops (signals, stop requests, concurrent requests).

    The tests stop it within a few hundred cycles; its length only makes sure that no machine,
    however fast its lockstep or slow its signal delivery, finishes the run before the stop
    arrives (the stop is what they test).
    """
    return write_trajectory(tmp_path_factory.mktemp("traj") / "long.json", periods=40)


@pytest.fixture
def make_config(tmp_path: Path) -> Callable[..., Path]:
    counter = itertools.count()

    def make(**kw: Any) -> Path:
        return write_config(tmp_path / f"acq{next(counter)}.toml", **kw)

    return make


def start_acquire(
    cfg: Path, trajectory: Path, out: Path, *, new_session: bool = False
) -> subprocess.Popen[bytes]:
    """``drivegain acquire`` in a subprocess (its own process group with ``new_session``)."""
    cmd = [sys.executable, "-m", "drivegain.cli", "acquire", "--config", str(cfg)]
    cmd += ["--trajectory", str(trajectory), "--out", str(out)]
    return subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=new_session
    )


def wait_for_cycles(part: Path, proc: subprocess.Popen[bytes], cycles: int) -> int:
    """Wait until the flushed .part holds at least ``cycles`` cycles; return how many."""
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        if part.exists():
            try:
                n = sum(1 for _ in iter_channel(part, "/joint_states"))
            except Exception:  # a chunk being written
                n = 0
            if n >= cycles:
                return n
        time.sleep(0.2)
    raise AssertionError("the run did not get going")


def start_until(
    cfg: Path, trajectory: Path, out: Path, cycles: int, *, new_session: bool = False
) -> tuple[subprocess.Popen[bytes], int]:
    """:func:`start_acquire`, then :func:`wait_for_cycles` on the run's ``.part`` beside
    ``out``: the process, and the cycles flushed when it got going."""
    proc = start_acquire(cfg, trajectory, out, new_session=new_session)
    return proc, wait_for_cycles(out.with_name(out.name + ".part"), proc, cycles)


def assert_at_rest(position: np.ndarray, period_s: float, cycles: int = 20) -> None:
    """The logged joint positions (cycles, n), rad, show a robot at rest over the last cycles.

    Held against the simulated current-loop noise, a joint at rest wanders by up to about 1e-3
    rad over 20 cycles, so cycle-to-cycle differences cannot tell rest from slow motion. The
    test is on the mean speed, a line fit over the last ``cycles`` (its noise: about 3e-3 rad/s
    at 4 ms), against the 0.5 rad/s and more of the test trajectories while they move.
    """
    t = np.arange(cycles) * period_s
    speed = np.polyfit(t, position[-cycles:], 1)[0]
    assert np.all(np.abs(speed) < 0.05), f"still moving: {speed} rad/s"


LongRun = Callable[..., tuple[subprocess.Popen[bytes], int, Path]]


@pytest.fixture
def long_run(tmp_path: Path, long_trajectory: Path) -> LongRun:
    """``long_run(cfg, cycles, new_session=False)``: :func:`start_until` of ``drivegain acquire``
    on :func:`long_trajectory` writing ``tmp_path/run.mcap``: the process, the cycles flushed
    when it got going, and the path of the log."""
    out = tmp_path / "run.mcap"

    def start(
        cfg: Path, cycles: int, *, new_session: bool = False
    ) -> tuple[subprocess.Popen[bytes], int, Path]:
        proc, seen = start_until(cfg, long_trajectory, out, cycles, new_session=new_session)
        return proc, seen, out

    return start


@pytest.fixture
def acquire_cli() -> SimpleNamespace:
    """``start``, ``wait_for_cycles`` and both at once (``start_until``) of a ``drivegain
    acquire`` subprocess, and ``assert_at_rest`` for its log."""
    return SimpleNamespace(
        start=start_acquire,
        wait_for_cycles=wait_for_cycles,
        start_until=start_until,
        assert_at_rest=assert_at_rest,
    )


class Notes:
    """A fake systemd notifier that keeps what it was told."""

    def __init__(self) -> None:
        self.messages: list[str] = []

    def notify(self, state: str) -> None:
        self.messages.append(state)


def wait_until(cond: Callable[[], Any], timeout: float = 30.0, what: str = "condition") -> Any:
    """Poll ``cond`` every 50 ms until it returns a true value, and return that value; fail the
    test after ``timeout`` seconds (a guard against a hang, not a timing check)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


@contextmanager
def serving(
    d: Daemon,
    *,
    stop: str = "test",
    join_s: float = 60.0,
    target: Callable[[], None] | None = None,
) -> Iterator[threading.Thread]:
    """Serve ``d`` on a thread (``target``, default ``d.serve``); on leaving, request its
    shutdown with the reason ``stop`` and join the thread for up to ``join_s`` seconds."""
    th = threading.Thread(target=target or d.serve, name="test-daemon")
    th.start()
    try:
        yield th
    finally:
        d.shutdown.request(stop)
        th.join(join_s)


@pytest.fixture
def daemon_kit(tmp_path: Path, make_config: Callable[..., Path]) -> SimpleNamespace:
    """Helpers of the in-process daemon tests.

    ``config(extra="", sock=None)``: the simulated cell's acquisition config with a ``[daemon]``
    table (``socket`` = ``sock``, default ``tmp_path/ctl.sock``; runs in ``tmp_path/runs``;
    ``extra`` further keys) and the socket path; ``serve``: :func:`serving`; ``wait``:
    :func:`wait_until`; ``Notes``: a notifier that keeps its messages.
    """

    def config(extra: str = "", sock: Path | None = None) -> tuple[AcquisitionConfig, Path]:
        sock = sock if sock is not None else tmp_path / "ctl.sock"
        text = f'socket = "{sock}"\noutput_dir = "{tmp_path / "runs"}"'
        if extra:
            text += f"\n{extra}"
        return load_acquisition_config(make_config(daemon=text)), sock

    return SimpleNamespace(config=config, serve=serving, wait=wait_until, Notes=Notes)


def _leaky_threads() -> set[threading.Thread]:
    return {
        t
        for t in threading.enumerate()
        if t.is_alive()
        and (t.name.startswith("drivegain") or "Notifier" in t.name or "can.notifier" in t.name)
    }


@pytest.fixture(autouse=True)
def no_leaked_threads() -> Iterator[None]:
    """Fail a test that leaves a bus reader, simulator, recorder or cycle thread running."""
    before = _leaky_threads()
    yield
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        leaked = _leaky_threads() - before
        if not leaked:
            return
        time.sleep(0.05)
    pytest.fail(f"threads left running: {sorted(t.name for t in leaked)}")
