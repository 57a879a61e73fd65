"""PNG plots of an identification (matplotlib, Agg backend: no display needed).

- ``torques.png``: measured (V·g) and computed (W·χ) joint torques per joint (the paper's Fig. 3),
- ``residuals.png``: their differences,
- ``alpha.png``: the α curve of IDIM-WTLS,
- ``singular_values.png``: singular values of the weighted WTLS matrix.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

from drivegain.identify.procedure import ProcedureResult

#: Most points drawn per curve (longer series are thinned for size, not for content).
MAX_POINTS = 4000


def _thin(n: int) -> slice:
    return slice(None, None, max(1, -(-n // MAX_POINTS)))


def _save(fig: Figure, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _series(result: ProcedureResult) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """(label, t, measured, computed) per run of the final case."""
    final = result.final
    out = []
    k = 0
    for label in ("unloaded", "loaded"):
        d = result.designs.get(label)
        if d is None:
            continue
        chi_l = None
        if d.loaded:
            chi_l = final.payloads[k].values
            k += 1
        out.append((label, d.run.t, d.torque(final.gains), d.model_torque(final.base, chi_l)))
    return out


def plot_torques(result: ProcedureResult, joint_names: list[str], path: Path) -> None:
    """Measured and computed torques per joint (loaded run if any, as in the paper's Fig. 3)."""
    series = _series(result)
    label, t, y, yh = series[-1]
    n = y.shape[1]
    fig, grid = plt.subplots(n, 1, figsize=(9, 1.7 * n), sharex=True, squeeze=False)
    axes = list(grid[:, 0])
    sl = _thin(t.size)
    for j, ax in enumerate(axes):
        ax.plot(t[sl], y[sl, j], lw=0.8, label="measured V·g")
        ax.plot(t[sl], yh[sl, j], lw=0.8, ls="--", label="computed W·χ")
        ax.set_ylabel(f"{joint_names[j]} N·m")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title(f"Joint torques, run '{label}' ({result.final.name} gains)")
    axes[-1].set_xlabel("time s")
    _save(fig, path)


def plot_residuals(result: ProcedureResult, joint_names: list[str], path: Path) -> None:
    """Residuals V·g − W·χ per joint, every run."""
    series = _series(result)
    n = series[0][2].shape[1]
    fig, grid = plt.subplots(n, 1, figsize=(9, 1.5 * n), sharex=True, squeeze=False)
    axes = list(grid[:, 0])
    for label, t, y, yh in series:
        sl = _thin(t.size)
        for j, ax in enumerate(axes):
            ax.plot(t[sl], (y - yh)[sl, j], lw=0.6, label=label)
    for j, ax in enumerate(axes):
        ax.set_ylabel(f"{joint_names[j]} N·m")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title("Residuals: measured − computed torque")
    axes[-1].set_xlabel("time s")
    _save(fig, path)


def plot_alpha(result: ProcedureResult, path: Path) -> bool:
    """The α curve; False (nothing written) when α was not searched."""
    if result.wtls is None or not result.wtls.alpha_curve:
        return False
    a, e = np.array(result.wtls.alpha_curve).T
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.semilogx(a, e, "o-", ms=3)
    ax.axvline(result.wtls.fit.alpha, color="k", ls=":", label=f"α = {result.wtls.fit.alpha:.3g}")
    ax.set_xlabel("α (weight of the V columns)")
    ax.set_ylabel("relative error norm (weighted)")
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    ax.ticklabel_format(axis="y", useOffset=False, style="plain")
    _save(fig, path)
    return True


def plot_singular_values(result: ProcedureResult, path: Path) -> bool:
    """Singular values of the weighted WTLS matrix; False when no WTLS was run."""
    if result.wtls is None:
        return False
    s = result.wtls.fit.tls.singular_values
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.semilogy(np.arange(1, s.size + 1), s, ".-")
    ax.semilogy([s.size - 1, s.size], s[-2:], "o", color="C3", label="two smallest")
    ax.set_xlabel("index")
    ax.set_ylabel("singular value")
    ax.set_title(f"WTLS matrix (gap ratio {result.wtls.fit.tls.gap:.3g})")
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    _save(fig, path)
    return True


def write_plots(result: ProcedureResult, joint_names: list[str], folder: Path) -> dict[str, str]:
    """Write every plot that applies into ``folder``; returns name -> file name."""
    out = {}
    plot_torques(result, joint_names, folder / "torques.png")
    out["torques"] = "torques.png"
    plot_residuals(result, joint_names, folder / "residuals.png")
    out["residuals"] = "residuals.png"
    if plot_alpha(result, folder / "alpha.png"):
        out["alpha"] = "alpha.png"
    if plot_singular_values(result, folder / "singular_values.png"):
        out["singular_values"] = "singular_values.png"
    return out
