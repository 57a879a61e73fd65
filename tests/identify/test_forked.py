"""Independent fits in a forked child (identify/forked.py): the same results as run in turn,
errors carried back with their context, a dead child reported, no fork where it is unsafe."""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
from dataclasses import fields, is_dataclass
from typing import Any

import numpy as np
import pytest

from drivegain.errors import IdentificationError, InputError
from drivegain.identify import crossval, forked, leaveout
from drivegain.identify.design import make_design
from drivegain.identify.procedure import Options, Problem, run_procedure

#: A fork is possible here at all (the suite's own threads aside, see ``fork_allowed``).
CAN_FORK = "fork" in multiprocessing.get_all_start_methods() and len(os.sched_getaffinity(0)) > 1
needs_fork = pytest.mark.skipif(not CAN_FORK, reason="no fork here (one CPU or no fork)")


@pytest.fixture
def fork_allowed(monkeypatch: pytest.MonkeyPatch) -> None:
    """Threads left by other tests of the suite (daemon threads of buses, notifiers) would make
    :func:`forked.fork_is_safe` say no; the children here touch no lock of theirs."""
    monkeypatch.setattr(forked, "fork_is_safe", lambda: True)


def _assert_same(x: Any, y: Any, where: str) -> None:
    """Field by field, arrays bit for bit (the same function on the same data)."""
    if is_dataclass(x) and not isinstance(x, type):
        assert type(x) is type(y), where
        for f in fields(x):
            _assert_same(getattr(x, f.name), getattr(y, f.name), f"{where}.{f.name}")
    elif isinstance(x, dict):
        assert list(x) == list(y), where
        for k in x:
            _assert_same(x[k], y[k], f"{where}[{k!r}]")
    elif isinstance(x, list | tuple):
        assert len(x) == len(y), where
        for i, (u, v) in enumerate(zip(x, y, strict=True)):
            _assert_same(u, v, f"{where}[{i}]")
    elif isinstance(x, np.ndarray):
        np.testing.assert_array_equal(x, y, err_msg=where)
    elif isinstance(x, float) and np.isnan(x):
        assert np.isnan(y), where
    else:
        assert x == y, where


def _record_children(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """From now on, what each forked child computes (its ``what``), in order of start."""
    children: list[str] = []
    real_start = forked.start

    def start(what, fn, *, parallel):  # type: ignore[no-untyped-def]
        pending = real_start(what, fn, parallel=parallel)
        if pending.forked:
            children.append(what)
        return pending

    monkeypatch.setattr(forked, "start", start)
    return children


@needs_fork
def test_forked_fits_equal_fits_in_turn(world, noisy_run, monkeypatch, fork_allowed) -> None:
    rng = np.random.default_rng(41)
    problem = Problem(
        robot=world.robot,
        bases=world.bases,
        unloaded=noisy_run(0, None, rng, duration=12.0, label="unloaded"),
        loaded=noisy_run(1, world.payload, rng, duration=12.0, label="loaded"),
        validation=noisy_run(2, world.validation, rng, duration=12.0, label="validation"),
    )
    # Case 2 under the gains' error model, whose covariance forks (the gate that would leave
    # out these runs' slow reversals and take Newey-West's σ instead held shut)
    monkeypatch.setattr(leaveout, "MISFIT_KAPPA", np.inf)
    monkeypatch.setattr(forked, "PARALLEL_EQUATIONS", 10**12)
    in_turn = run_procedure(problem, Options())

    monkeypatch.setattr(forked, "PARALLEL_EQUATIONS", 0)
    children = _record_children(monkeypatch)
    in_children = run_procedure(problem, Options())
    # Run a's cross-validation factors, Case 1, the least-squares start (while both runs are
    # reduced at κ = 0 here), the reduction of run a at κ̂, the covariance's run a, the other
    # friction form, then run a's share of the covariance of Case 2 and of the validation's
    assert children[:3] == ["cross-validation factors", "Case 1 fit", "least-squares start"]
    assert children[-4:] == [
        "maximum-likelihood covariance",
        "friction forms",
        "Case 2 covariance",
        "Case 2 covariance",
    ]
    assert len(children) > 7 and set(children[3:-4]) == {"maximum-likelihood reduction"}
    assert len(in_children.forms) == 2
    _assert_same(in_children, in_turn, "result")


def _bad_file() -> None:
    raise InputError("no such column 'q7'", file="run.mcap", key="joint_states")


@needs_fork
def test_child_error_comes_back_with_its_context(fork_allowed: None) -> None:
    pending = forked.start("Case 1 fit", _bad_file, parallel=True)
    assert pending.forked
    with pytest.raises(InputError) as caught:
        pending.result()
    assert caught.value.file == "run.mcap"
    assert caught.value.key == "joint_states"
    assert "no such column 'q7'" in str(caught.value)


def _die_if_child(parent: int) -> None:
    if os.getpid() != parent:  # never this process, whatever happened to the fork
        os._exit(3)
    raise AssertionError("ran in the parent: not forked")


@needs_fork
def test_dead_child_is_reported_by_what_it_computed(fork_allowed: None) -> None:
    parent = os.getpid()
    pending = forked.start("friction forms", lambda: _die_if_child(parent), parallel=True)
    assert pending.forked
    with pytest.raises(IdentificationError, match="friction forms: the process computing it"):
        pending.result()


def test_no_fork_while_another_thread_runs() -> None:
    stop = threading.Event()
    other = threading.Thread(target=stop.wait, daemon=True)
    other.start()
    try:
        assert not forked.fork_is_safe()
        pending = forked.start("Case 1 fit", lambda: os.getpid(), parallel=True)
        assert not pending.forked
        assert pending.result() == os.getpid()  # computed here, in this process
    finally:
        stop.set()
        other.join()


def test_small_work_is_not_forked() -> None:
    pending = forked.start("Case 1 fit", lambda: os.getpid(), parallel=False)
    assert not pending.forked and pending.result() == os.getpid()


def _nested_start() -> tuple[bool, bool]:
    """In a forked child: whether a second start forks again, and whether its work ran here."""
    inner = forked.start("Case 1 fit", lambda: os.getpid(), parallel=True)
    return inner.forked, inner.result() == os.getpid()


@needs_fork
def test_a_forked_child_does_not_fork_again(monkeypatch: pytest.MonkeyPatch) -> None:
    """A child is daemonic, and a daemonic process may not have children: its own start runs the
    work in place instead of failing with an internal error."""
    parent, real = os.getpid(), forked.fork_is_safe
    # The suite's threads would make the parent say no; the child must use the real check.
    monkeypatch.setattr(forked, "fork_is_safe", lambda: os.getpid() == parent or real())
    outer = forked.start("friction forms", _nested_start, parallel=True)
    assert outer.forked
    assert outer.result() == (False, True)


def _big_result() -> bytes:
    return bytes(16 * 2**20)  # far more than a pipe holds: the child blocks sending it


@needs_fork
def test_cancel_ends_a_child_that_ignores_sigterm(fork_allowed: None) -> None:
    """A child that inherited an ignored (or handled) SIGTERM, blocked sending a result nobody
    reads, still ends on cancel: found as a hang of the whole suite."""
    old = signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        pending = forked.start("friction forms", _big_result, parallel=True)
    finally:
        signal.signal(signal.SIGTERM, old)
    assert pending.forked
    done = threading.Event()
    canceller = threading.Thread(target=lambda: (pending.cancel(), done.set()), daemon=True)
    canceller.start()
    # Not a timing assertion: the bound is minutes for a step that takes milliseconds; failing
    # it means cancel would have waited forever.
    assert done.wait(120.0), "cancel did not end the child"


@needs_fork
def test_factors_split_in_a_child_equal_those_in_turn(
    world, noisy_run, monkeypatch, fork_allowed
) -> None:
    rng = np.random.default_rng(42)
    form = world.robot.wrist_friction
    designs = [
        make_design(
            noisy_run(k, pay, rng, duration=6.0, label=f"r{k}"),
            world.bases[form],
            form,
            world.robot,
        )
        for k, pay in ((0, None), (1, world.payload))
    ]
    in_turn = crossval.split_factors(designs)
    children = _record_children(monkeypatch)
    in_child = crossval.split_factors(designs, parallel=True)
    assert children == ["cross-validation factors"]
    _assert_same(in_child, in_turn, "factors")
