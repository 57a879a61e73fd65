"""CANopen CiA 402 drives (master side), simulated drives and robot, CAN bus factory.

Modules: :mod:`.bus` (python-can bus from the ``[bus]`` table, bus-load arithmetic),
:mod:`.cia402` (drive state machine), :mod:`.objects` (object indexes, PDO layouts, error codes),
:mod:`.master` (the master: boot, enable, cyclic exchange, supervision), :mod:`.sim` (the
simulated cell: drives + physics on a CAN channel, ``[simulation]`` table), :mod:`.simdrive`
(one simulated drive), :mod:`.physics` (forward dynamics and drive control loops),
:mod:`.faults` (injectable faults), :mod:`.gcfreeze` (short garbage-collector pauses while drives
are supervised). Import the module you need: this package imports nothing.
"""
