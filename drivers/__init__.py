"""CANopen CiA 402 drives (master side), simulated drives and robot, CAN bus factory."""
