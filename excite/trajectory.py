"""The motion API on top of the trajectory file.

The ``TRAJ.json`` reader and writer live in :mod:`drivegain.formats.trajectory` and are
re-exported here with the motion API (:class:`Motion`, :func:`plan_motion`, :func:`plan_stop`,
:func:`check_limits`) of :mod:`.motion` and :mod:`.limits`.
"""

from __future__ import annotations

import numpy as np

from drivegain.config.robot import Robot
from drivegain.excite.limits import check_limits
from drivegain.excite.motion import Motion, Phase, check_motion, plan_motion, plan_stop
from drivegain.formats.trajectory import (
    FORMAT_VERSION,
    ExcitationFile,
    load_trajectory,
    save_trajectory,
    trajectory_document,
)

__all__ = [
    "FORMAT_VERSION",
    "ExcitationFile",
    "Motion",
    "Phase",
    "check_limits",
    "check_motion",
    "load_trajectory",
    "plan_excitation",
    "plan_motion",
    "plan_stop",
    "save_trajectory",
    "trajectory_document",
]


def plan_excitation(
    excitation: ExcitationFile, robot: Robot, q_start: np.ndarray, periods: int | None = None
) -> Motion:
    """:func:`plan_motion` of a trajectory file's series, with the working limits stored in the
    file (if any), after checking that the file was made for ``robot``'s joints."""
    excitation.check_robot(robot)
    return plan_motion(robot, excitation.fourier, q_start, periods, limits=excitation.limits)
