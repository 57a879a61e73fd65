"""The BLAS thread limit applies to library calls, not only to the command line (issue 16,
item 8)."""

from __future__ import annotations

import pytest

import drivegain.identify.procedure as procedure
from drivegain.config.robot import WristFriction
from drivegain.identify.blas import _controls, limited_blas_threads
from drivegain.identify.procedure import Options, Problem, run_procedure


def test_run_procedure_limits_openblas_threads(world, exact_run, monkeypatch) -> None:
    if not _controls():
        pytest.skip("no OpenBLAS control found in this process")
    seen: list[list[int]] = []
    real = procedure.fit_case

    def spy(*args, **kwargs):
        seen.append([getter() for _, getter in _controls()])
        return real(*args, **kwargs)

    monkeypatch.setattr(procedure, "fit_case", spy)
    a = exact_run(0, None, label="unloaded")
    problem = Problem(robot=world.robot, bases=world.bases, unloaded=a)
    # A caller of the library with two threads (the test session itself runs with one).
    with limited_blas_threads(2):
        before = [getter() for _, getter in _controls()]
        run_procedure(problem, Options(friction=WristFriction.PHYSICAL))
        after = [getter() for _, getter in _controls()]
    assert seen and all(n == 1 for call in seen for n in call)
    assert before == after  # restored for the caller
