"""The master's own heartbeat and the drives' consumer of it: configuration, and the drives
stopping the robot when the master dies (lockstep; the realtime case, with a SIGKILLed master
process, is tests/acquire/test_simprocess.py; the frames are proven byte for byte in
test_master_script.py and test_simdrive_script.py)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivegain.drivers.cia402 import State
from drivegain.drivers.master import Master, MasterHeartbeat
from drivegain.drivers.sim import SimConfig
from drivegain.errors import ConfigError

PERIOD = 0.004
#: Wall-clock bound against a hang only.
HANG_GUARD_S = 30.0


def test_a_drive_with_the_master_node_id_is_refused(one_joint_robot, scripted):
    rig = scripted([])
    with pytest.raises(ConfigError, match="master's node id 1 is a drive's node id"):
        Master(one_joint_robot, rig.network, period_s=PERIOD, heartbeat=MasterHeartbeat(1))
    assert rig.network.nodes == {}


@pytest.mark.parametrize(("node_id", "period_s"), [(0, 0.1), (128, 0.1), (127, 0.0), (127, 30.0)])
def test_impossible_master_heartbeats_are_refused(node_id, period_s):
    with pytest.raises(ConfigError):
        MasterHeartbeat(node_id, period_s)


def test_the_drives_stop_the_robot_when_the_master_dies_in_lockstep(tx40, channel, rig_factory):
    """The master's network vanishes mid-motion (no close, no more heartbeat). Nothing advances
    the simulated clock any more, so it follows the wall clock: each drive's consumer times out,
    its fault reaction ramps the motor to rest, then FAULT with EMCY 0x8130."""
    t = np.arange(round(0.6 / PERIOD)) * PERIOD
    amp = np.array([0.6, 0.4, 0.5, 0.8, 0.6, 1.0])
    targets = amp * (1.0 - np.cos(2 * np.pi * 0.5 * (t[:, None] + PERIOD))) / 2.0
    with rig_factory(tx40, channel, SimConfig(), PERIOD) as rig:
        rig.master.boot()
        rig.master.enable()
        for q in targets:
            rig.master.cycle(q)
        moving = float(np.abs(rig.cell.physics.qd).max())
        rig.network.disconnect()  # the master is gone
        deadline = time.monotonic() + HANG_GUARD_S
        while time.monotonic() < deadline:
            with rig.cell.locked():
                done = not rig.cell.physics.any_powered
            if done:
                break
            time.sleep(0.02)
        with rig.cell.locked():
            states = {d.node_id: d.state for d in rig.cell.drives.values()}
            codes = {d.error_code for d in rig.cell.drives.values()}
            speed = float(np.abs(rig.cell.physics.qd).max())
        assert rig.cell.errors == []
    assert moving > 0.3
    assert set(states.values()) == {State.FAULT}
    assert codes == {0x8130}
    assert speed == 0.0
