"""The garbage collector's freeze and the realtime policy built on it: what a hold keeps out of
collections, nesting, SCHED_FIFO for a cycle thread and its restoration, CPU affinity. (That a
rig holds the policy from open to close, across a daemon's runs, is tested in tests/acquire.)"""

from __future__ import annotations

import errno
import gc
import os
import pickle
import threading
import weakref
from collections.abc import Callable
from typing import Any

import pytest

from drivegain.drivers import gcfreeze
from drivegain.drivers.realtime import FifoOutcome, RealtimePolicy
from drivegain.errors import ConfigError, UsageError


class _Node:
    def __init__(self) -> None:
        self.other: _Node | None = None


def _garbage_cycle() -> weakref.ref[_Node]:
    """An unreachable reference cycle: only the cyclic collector can free it."""
    a, b = _Node(), _Node()
    a.other, b.other = b, a
    return weakref.ref(a)


def test_a_hold_keeps_existing_objects_out_of_collections_until_the_last_release() -> None:
    assert gcfreeze.holders() == 0
    gc.collect()
    before = _garbage_cycle()
    gcfreeze.hold()
    try:
        assert gc.get_freeze_count() > 0
        gcfreeze.hold()  # a second master
        during = _garbage_cycle()
        gc.collect()
        assert during() is None  # allocated during the hold: collected as usual
        assert before() is not None  # frozen: not walked
        gcfreeze.release()
        assert gcfreeze.holders() == 1 and gc.get_freeze_count() > 0
        gc.collect()
        assert before() is not None
    finally:
        gcfreeze.release()
    assert gcfreeze.holders() == 0 and gc.get_freeze_count() == 0
    gc.collect()
    assert before() is None


def test_release_without_hold_is_an_error() -> None:
    with pytest.raises(UsageError, match="without a hold"):
        gcfreeze.release()


def test_only_a_first_hold_collects_before_freezing() -> None:
    gc.collect()
    garbage = _garbage_cycle()
    gcfreeze.hold(collect=True)
    try:
        assert garbage() is None  # collected, not frozen for the hold's life
        # under a hold drives may be supervised: a second hold makes no pause
        kept = _garbage_cycle()
        gcfreeze.hold(collect=True)
        assert kept() is not None
        gcfreeze.release()
    finally:
        gcfreeze.release()
    gc.collect()
    assert kept() is None


def test_refreeze_freezes_without_collecting_only_while_held() -> None:
    gc.collect()
    assert gcfreeze.refreeze() is False and gc.get_freeze_count() == 0
    gcfreeze.hold()
    try:
        frozen_before = gc.get_freeze_count()
        setup = _garbage_cycle()  # what a set-up left: kept, not walked
        assert gcfreeze.refreeze() is True and gc.get_freeze_count() > frozen_before
        later = _garbage_cycle()
        gc.collect()
        assert setup() is not None and later() is None
    finally:
        gcfreeze.release()
    gc.collect()
    assert setup() is None  # given back at the last release


# -- the realtime policy -----------------------------------------------------------------------


def test_the_process_part_nests_on_the_reference_counted_freeze() -> None:
    outer, inner = RealtimePolicy(), RealtimePolicy(fifo_priority=10)
    with outer.process():
        assert gcfreeze.holders() == 1 and gc.get_freeze_count() > 0
        with inner.process():
            assert gcfreeze.holders() == 2
        assert gcfreeze.holders() == 1 and gc.get_freeze_count() > 0
    assert gcfreeze.holders() == 0 and gc.get_freeze_count() == 0
    with RealtimePolicy(gc_freeze=False).process():
        assert gcfreeze.holders() == 0
        RealtimePolicy(gc_freeze=False).refreeze()  # nothing to refreeze without the freeze
        assert gc.get_freeze_count() == 0


def test_the_process_part_releases_on_an_exception() -> None:
    with pytest.raises(KeyError), RealtimePolicy().process():
        raise KeyError("boom")
    assert gcfreeze.holders() == 0


def _on_a_thread(fn: Callable[[], Any]) -> Any:
    """``fn()`` on a fresh thread (scheduling changes never reach the test's own thread)."""
    out: dict[str, Any] = {}

    def target() -> None:
        try:
            out["value"] = fn()
        except BaseException as exc:
            out["error"] = exc

    th = threading.Thread(target=target, name="test-realtime")
    th.start()
    th.join(30)
    if "error" in out:
        raise out["error"]
    return out["value"]


def _scheduling() -> tuple[int, int]:
    return os.sched_getscheduler(0), os.sched_getparam(0).sched_priority


def test_no_fifo_asked_leaves_the_thread_alone() -> None:
    def body() -> tuple[FifoOutcome, tuple[int, int], tuple[int, int]]:
        before = _scheduling()
        with RealtimePolicy().cycle_thread() as fifo:
            inside = _scheduling()
        assert _scheduling() == before
        return fifo, before, inside

    fifo, before, inside = _on_a_thread(body)
    assert fifo == FifoOutcome(0, False) and fifo.describe() == "not asked"
    assert inside == before


def test_a_refused_fifo_is_reported_and_the_scheduling_is_untouched(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls: list[tuple[int, int]] = []

    def refuse(pid: int, policy: int, param: os.sched_param) -> None:
        calls.append((pid, policy))
        raise PermissionError(errno.EPERM, os.strerror(errno.EPERM))

    monkeypatch.setattr(os, "sched_setscheduler", refuse)

    def body() -> tuple[FifoOutcome, tuple[int, int], tuple[int, int], tuple[int, int]]:
        before = _scheduling()
        with RealtimePolicy(fifo_priority=50).cycle_thread() as fifo:
            inside = _scheduling()
        return fifo, before, inside, _scheduling()

    fifo, before, inside, after = _on_a_thread(body)
    assert not fifo.granted and fifo.priority == 50
    assert fifo.refusal == os.strerror(errno.EPERM) and fifo.describe().startswith("refused (")
    assert inside == before == after
    assert calls == [(0, os.SCHED_FIFO)]  # asked once; nothing to restore


def test_a_granted_fifo_is_undone_after_the_block_even_on_an_exception() -> None:
    def body() -> tuple[list[Any], tuple[int, int]]:
        before = _scheduling()
        seen: list[Any] = []
        policy = RealtimePolicy(fifo_priority=5)
        with policy.cycle_thread() as fifo:
            if not fifo.granted:
                pytest.skip(f"SCHED_FIFO refused here: {fifo.refusal}")
            seen.append(_scheduling())
            # nested: the inner block restores the outer block's priority
            with RealtimePolicy(fifo_priority=7).cycle_thread() as inner:
                seen.append((inner.granted, _scheduling()))
            seen.append(_scheduling())
        seen.append(_scheduling())
        with pytest.raises(RuntimeError), policy.cycle_thread():
            raise RuntimeError("the cycle loop failed")
        seen.append(_scheduling())
        return seen, before

    seen, before = _on_a_thread(body)
    fifo5, fifo7 = (os.SCHED_FIFO, 5), (os.SCHED_FIFO, 7)
    assert seen == [fifo5, (True, fifo7), fifo5, before, before], seen
    assert before[0] != os.SCHED_FIFO


def test_the_cpu_set_applies_to_every_thread_and_is_restored() -> None:
    original = os.sched_getaffinity(0)
    one = frozenset({min(original)})
    started = threading.Event()
    stop = threading.Event()
    seen: dict[str, set[int]] = {}

    def older() -> None:  # a thread that existed before the policy was entered
        started.set()
        stop.wait(30)
        seen["older_after"] = os.sched_getaffinity(0)

    th = threading.Thread(target=older, name="test-affinity")
    th.start()
    started.wait(30)
    try:
        with RealtimePolicy(gc_freeze=False, cpus=one).process():
            seen["inside"] = os.sched_getaffinity(0)
            seen["older_inside"] = os.sched_getaffinity(th.native_id or 0)
    finally:
        stop.set()
        th.join(30)
    assert seen["inside"] == seen["older_inside"] == set(one)
    assert os.sched_getaffinity(0) == seen["older_after"] == original


def test_a_policy_is_checked_and_travels_to_a_child_process() -> None:
    with pytest.raises(ConfigError, match=r"0\.\.99"):
        RealtimePolicy(fifo_priority=100)
    with pytest.raises(ConfigError, match="empty CPU set"):
        RealtimePolicy(cpus=frozenset())
    policy = RealtimePolicy(fifo_priority=80, cpus=frozenset({0}))
    assert pickle.loads(pickle.dumps(policy)) == policy
