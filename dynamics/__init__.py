"""The robot model every stage shares: kinematics and inertia (MDH or URDF → Pinocchio), the
standard parameter layout, the IDIM regressor, base parameters and the transmission (gains and
the coupled wrist).

Modules: :mod:`.model`, :mod:`.params`, :mod:`.regressor`, :mod:`.base`, :mod:`.transmission`.
Plain functions on numpy arrays; nothing here reads a log or talks to a drive.
"""
