"""The forked plotting worker (issue 19): draws what it is sent, and on any failure the figures
are drawn in the calling process, which then raises the real error."""

from __future__ import annotations

import multiprocessing
import os
import time
from pathlib import Path

import numpy as np
import pytest

from drivegain.identify import plots


@pytest.fixture
def worker(monkeypatch):
    # Threads other tests of the suite leave behind for a moment (bus notifiers) would make the
    # fork-safety rule say no; the worker touches no lock of theirs.
    fork = "fork" in multiprocessing.get_all_start_methods()
    monkeypatch.setattr(plots, "fork_is_safe", lambda: fork)
    plots.start_worker()
    yield plots._WORKER
    plots.stop_worker()


def _jobs(folder: Path) -> list[plots.Job]:
    curve = np.array([[0.5, 0.2], [1.0, 0.1], [5.0, 0.15]])
    return [(plots.draw_alpha, (curve, 1.0, folder / "alpha.png"))]


def test_the_worker_draws_the_jobs(worker, tmp_path: Path) -> None:
    if worker is None:
        pytest.skip("no fork here, or other threads run: figures are drawn in-process")
    assert worker.run(_jobs(tmp_path))
    assert (tmp_path / "alpha.png").stat().st_size > 1000
    plots.stop_worker()
    assert not worker.proc.is_alive()


def test_a_failing_job_is_redrawn_here_and_raises(worker, tmp_path: Path, monkeypatch) -> None:
    missing = tmp_path / "no such folder"
    monkeypatch.setattr(plots, "plot_jobs", lambda *_a: (_jobs(missing), {"alpha": "alpha.png"}))
    with pytest.raises(FileNotFoundError):
        plots.write_plots(None, [], missing)  # type: ignore[arg-type]
    if worker is not None:  # still serving after the failure
        assert worker.run(_jobs(tmp_path))


def test_jobs_are_split_with_a_forked_child(tmp_path: Path, monkeypatch) -> None:
    fork = "fork" in multiprocessing.get_all_start_methods()
    monkeypatch.setattr(plots, "fork_is_safe", lambda: fork)
    curve = np.array([[0.5, 0.2], [1.0, 0.1], [5.0, 0.15]])
    jobs = [(plots.draw_alpha, (curve, 1.0, tmp_path / f"alpha{k}.png")) for k in range(3)]
    assert plots.draw_split(jobs)
    assert all((tmp_path / f"alpha{k}.png").stat().st_size > 1000 for k in range(3))
    missing = tmp_path / "no such folder"
    # a failure in the child (even jobs) is reported; one here (odd jobs) raises
    if fork and len(os.sched_getaffinity(0)) > 1:
        assert not plots.draw_split([(plots.draw_alpha, (curve, 1.0, missing / "a.png")), jobs[1]])
    with pytest.raises(FileNotFoundError):
        plots.draw_split([jobs[0], (plots.draw_alpha, (curve, 1.0, missing / "b.png"))])


def _slow_job(pid_file: Path) -> None:
    """A figure that takes forever: writes its process id, then waits."""
    pid_file.write_text(str(os.getpid()))
    time.sleep(600)


def _alive(pid: int) -> bool:
    """Running (a zombie nobody has reaped yet counts as ended)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def test_a_killed_worker_takes_its_drawing_child_with_it(tmp_path: Path, monkeypatch) -> None:
    """The worker is killed when an identification stops early; the child it forked to draw
    half the figures must not go on writing into a report folder being removed."""
    if "fork" not in multiprocessing.get_all_start_methods() or len(os.sched_getaffinity(0)) < 2:
        pytest.skip("no fork here, or one CPU: the worker draws every figure itself")
    monkeypatch.setattr(plots, "fork_is_safe", lambda: True)
    child_pid, here_pid = tmp_path / "child", tmp_path / "here"
    jobs = [(_slow_job, (child_pid,)), (_slow_job, (here_pid,))]
    ctx = multiprocessing.get_context("fork")
    worker = ctx.Process(target=plots.draw_split, args=(jobs,), daemon=True)
    worker.start()
    # Liveness waits, not timing: each bound is minutes for steps of milliseconds.
    deadline = time.monotonic() + 120.0
    while not (child_pid.exists() and child_pid.read_text()) and time.monotonic() < deadline:
        time.sleep(0.01)
    pid = int(child_pid.read_text())
    assert pid != worker.pid and _alive(pid)
    worker.kill()
    worker.join()
    deadline = time.monotonic() + 120.0
    while _alive(pid) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not _alive(pid), "the drawing child outlived the killed worker"
