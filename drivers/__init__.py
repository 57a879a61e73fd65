"""CANopen CiA 402 drives (master side), simulated drives and robot, CAN bus factory.

Master side: :mod:`.master` (the facade: boot, enable, cyclic exchange, stop, close) over
:mod:`.link` (time limits, the per-drive record, typed SDO access), :mod:`.configure` (SDO set-up
and PDO mapping through canopen's PDO API), :mod:`.statewalk` (the CiA 402 walk),
:mod:`.exchange` (SYNC, RPDO targets, TPDOs tagged by SYNC counter) and :mod:`.supervisor`
(heartbeats, EMCY, error frames, faults and events), :mod:`.heartbeat` (the master's own
heartbeat, which the drives' consumers watch); :mod:`.simtime` (the clock supervision counts:
wall, or lockstep's simulated clock shared with the simulated drives); :mod:`.cia402` (drive
state machine),
:mod:`.objects` (object indexes, PDO layouts, error codes), :mod:`.bus` (python-can bus from the
``[bus]`` table, bus-load arithmetic), :mod:`.clock` (lockstep or realtime).

Simulation: :mod:`.sim` (the simulated cell: drives + physics on a CAN channel), :mod:`.simconfig`
(its ``[simulation]`` table), :mod:`.simdrive` (one simulated drive), :mod:`.simclock` (the
cell's clock, realtime integrator, heartbeat consumer of each drive), :mod:`.physics` (forward
dynamics and drive control loops), :mod:`.faults` (injectable faults), :mod:`.simprocess` and
:mod:`.ipcbus` (the drives in a process of their own).

Process policy: :mod:`.realtime` and :mod:`.gcfreeze` (garbage-collector freeze, SCHED_FIFO).
Import the module you need: this package imports nothing.
"""
