"""PNG of a motion's joint trajectories with the limits drawn."""

from __future__ import annotations

import io

import numpy as np

from drivegain.config.robot import Robot
from drivegain.excite.limits import ExcitationLimits
from drivegain.excite.motion import Motion, Phase

_PHASE_COLOURS = {
    Phase.APPROACH: "#dbe9f6",
    Phase.RETREAT: "#f6e3db",
    Phase.STOP: "#f6dbdb",
}


def render_motion_png(
    robot: Robot,
    motion: Motion,
    limits: ExcitationLimits | None = None,
    title: str = "",
    rate_hz: float = 200.0,
) -> bytes:
    """Plot position, velocity and acceleration of every joint over the whole motion.

    The robot's limits are drawn as red dashed lines, the working limits (with margins) as
    grey dotted lines; approach and retreat are shaded.

    Returns
    -------
    bytes
        The PNG image.
    """
    # A bare Figure renders with Agg and leaves pyplot's global state alone.
    from matplotlib.figure import Figure

    t = np.arange(0.0, motion.duration_s + 0.5 / rate_hz, 1.0 / rate_hz)
    q, qd, qdd = motion.sample(t)
    n = robot.n
    # Fixed margins: the constrained layout solver took longer than the drawing (18 axes).
    height = 2.0 * n + 1
    fig = Figure(figsize=(13, height))
    fig.subplots_adjust(
        left=0.06, right=0.99, bottom=0.5 / height, top=1 - 0.8 / height, wspace=0.22, hspace=0.12
    )
    axes = fig.subplots(n, 3, sharex=True, squeeze=False)
    hard = [
        (robot.lower, robot.upper),
        (-robot.velocity_limits, robot.velocity_limits),
        (-robot.acceleration_limits, robot.acceleration_limits),
    ]
    work = None
    if limits is not None:
        work = [
            (limits.lower, limits.upper),
            (-limits.velocity, limits.velocity),
            (-limits.acceleration, limits.acceleration),
        ]
    labels = ("position (rad)", "velocity (rad/s)", "acceleration (rad/s²)")
    for j in range(n):
        for k, x in enumerate((q, qd, qdd)):
            ax = axes[j, k]
            for phase, (t0, t1) in motion.phase_bounds.items():
                if phase in _PHASE_COLOURS:
                    ax.axvspan(t0, t1, color=_PHASE_COLOURS[phase], lw=0)
            ax.plot(t, x[:, j], color="#1f4e79", lw=0.9)
            for v in (hard[k][0][j], hard[k][1][j]):
                ax.axhline(v, color="#c00000", ls="--", lw=0.8)
            if work is not None:
                for v in (work[k][0][j], work[k][1][j]):
                    ax.axhline(v, color="#808080", ls=":", lw=0.8)
            if j == 0:
                ax.set_title(labels[k], fontsize=9)
            if k == 0:
                ax.set_ylabel(robot.joints[j].name)
            ax.tick_params(labelsize=7)
    for k in range(3):
        axes[-1, k].set_xlabel("time (s)")
    if title:
        fig.suptitle(title, fontsize=10)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    return buf.getvalue()
