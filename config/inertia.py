"""Physical consistency of rigid-body inertial parameters."""

from __future__ import annotations

import numpy as np


def inertia_matrix(inertia6: np.ndarray) -> np.ndarray:
    """3x3 symmetric tensor from ``[XX, XY, XZ, YY, YZ, ZZ]`` (kg·m², tensor elements)."""
    xx, xy, xz, yy, yz, zz = (float(v) for v in inertia6)
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])


def physical_violation(mass: float, first_moment: np.ndarray, inertia6: np.ndarray) -> str | None:
    """Why the inertial parameters are not those of a real body, or ``None`` if they are.

    Parameters
    ----------
    mass
        Mass, kg.
    first_moment
        ``[MX, MY, MZ]``, kg·m, in the body frame.
    inertia6
        ``[XX, XY, XZ, YY, YZ, ZZ]`` at the frame origin, kg·m², tensor elements.

    Returns
    -------
    str or None
        A short reason (mass not positive, inertia about the centre of mass not positive
        definite, triangle inequality violated) or ``None``.
    """
    if not mass > 0.0:
        return f"mass must be > 0 kg, got {mass}"
    c = np.asarray(first_moment, dtype=float) / mass
    i_origin = inertia_matrix(inertia6)
    # Parallel-axis theorem back to the centre of mass.
    i_com = i_origin - mass * (float(c @ c) * np.eye(3) - np.outer(c, c))
    eig = np.linalg.eigvalsh(i_com)
    scale = max(float(np.max(np.abs(eig))), 1e-12)
    if eig[0] <= -1e-9 * scale:
        return (
            "inertia about the centre of mass is not positive definite "
            f"(eigenvalues {', '.join(f'{e:.4g}' for e in eig)} kg·m²)"
        )
    e1, e2, e3 = eig
    if e1 + e2 < e3 * (1.0 - 1e-9):
        return (
            "principal moments about the centre of mass violate the triangle inequality "
            f"({e1:.4g} + {e2:.4g} < {e3:.4g} kg·m²)"
        )
    return None
