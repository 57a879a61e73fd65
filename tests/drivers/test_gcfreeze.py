"""The garbage collector's freeze while drives are supervised: what a hold keeps out of
collections, nesting, and that a master holds it from boot to close."""

from __future__ import annotations

import gc
import weakref

import pytest

from drivegain.drivers import gcfreeze
from drivegain.drivers.sim import SimConfig


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
    with pytest.raises(RuntimeError, match="without a hold"):
        gcfreeze.release()


def test_a_master_holds_the_freeze_from_boot_to_close(tx40, channel, rig_factory, fast) -> None:
    with rig_factory(tx40, channel, SimConfig(), 0.004, fast) as rig:
        assert gcfreeze.holders() == 0
        rig.master.boot()
        assert gcfreeze.holders() == 1
        rig.master.boot()  # booting again does not hold twice
        assert gcfreeze.holders() == 1
        rig.master.close()
        assert gcfreeze.holders() == 0
        rig.master.close()
    assert gcfreeze.holders() == 0
