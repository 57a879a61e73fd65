"""PNG plots of an identification (matplotlib, Agg backend: no display needed).

- ``torques_<run>.png``, one per run: measured (V·g) and computed (W·χ) joint torques per joint
  (the paper's Fig. 3) and, under each joint, their difference on its own scale,
- ``alpha.png``: the α curve of IDIM-WTLS (what the choice of α was made from),
- ``singular_values.png``: singular values of the weighted WTLS matrix and the gap that makes
  the gains well determined.

matplotlib is imported by the functions that draw, so a command that writes no plots
(``--no-plots``) never loads it; :func:`write_plots` is the single entry point.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from drivegain.identify.procedure import ProcedureResult

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: Most points drawn per curve (longer series are thinned for size, not for content).
MAX_POINTS = 4000
#: Runs drawn, in this order (the validation run has its own payload and is not re-fitted).
RUNS = ("unloaded", "loaded")


def _pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend (imported on first use: it takes ~0.3 s)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _thin(n: int) -> slice:
    return slice(None, None, max(1, -(-n // MAX_POINTS)))


def _save(fig: Figure, path: Path) -> None:
    plt = _pyplot()
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def _series(result: ProcedureResult) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """(label, t, measured, computed) per run of the final case."""
    final = result.final
    out = []
    k = 0
    for label in RUNS:
        d = result.designs.get(label)
        if d is None:
            continue
        chi_l = None
        if d.loaded:
            chi_l = final.payloads[k].values
            k += 1
        out.append((label, d.run.t, d.torque(final.gains), d.model_torque(final.base, chi_l)))
    return out


def plot_torques(
    label: str,
    t: np.ndarray,
    measured: np.ndarray,
    computed: np.ndarray,
    joint_names: list[str],
    case: str,
    path: Path,
) -> None:
    """One run: per joint, measured and computed torque and, below, their difference.

    Parameters
    ----------
    label
        The run (``unloaded``, ``loaded``).
    t
        Time, s, (N,).
    measured, computed
        V·g and W·χ, N·m, (N, n).
    joint_names
        Axis labels.
    case
        The case whose gains and parameters were used (for the title).
    path
        The PNG written.
    """
    plt = _pyplot()
    n = measured.shape[1]
    fig = plt.figure(figsize=(10, 2.3 * n), layout="constrained")
    # per joint a tall torque axis and a short difference axis with its own (smaller) scale
    grid = fig.add_gridspec(2 * n, 1, height_ratios=[3, 1.3] * n)
    sl = _thin(t.size)
    first = None
    for j in range(n):
        ax = fig.add_subplot(grid[2 * j], sharex=first)
        first = first or ax
        ax.plot(t[sl], measured[sl, j], lw=0.8, label="measured V·g")
        ax.plot(t[sl], computed[sl, j], lw=0.8, ls="--", label="computed W·χ")
        ax.set_ylabel(f"{joint_names[j]}\nN·m")
        ax.grid(alpha=0.3)
        ax.tick_params(labelbottom=False)
        diff = measured[:, j] - computed[:, j]
        rms = float(np.sqrt(np.mean(diff**2))) if diff.size else float("nan")
        ad = fig.add_subplot(grid[2 * j + 1], sharex=first)
        ad.plot(t[sl], diff[sl], lw=0.6, color="C3")
        ad.axhline(0.0, color="k", lw=0.5)
        ad.set_ylabel("diff.\nN·m", fontsize=8)
        ad.text(
            0.995,
            0.92,
            f"measured − computed, RMS {rms:.3g} N·m",
            transform=ad.transAxes,
            ha="right",
            va="top",
            fontsize=7,
        )
        ad.grid(alpha=0.3)
        if j < n - 1:
            ad.tick_params(labelbottom=False)
        else:
            ad.set_xlabel("time s")
        if j == 0:
            ax.legend(loc="upper right", fontsize=8)
            ax.set_title(
                f"Joint torques, run '{label}' ({case} gains and parameters); below each "
                "joint: their difference on its own scale"
            )
    _save(fig, path)


def plot_alpha(result: ProcedureResult, path: Path) -> bool:
    """The α curve; False (nothing written) when α was not searched."""
    w = result.wtls
    if w is None or w.fit is None or not w.alpha_curve:  # no α search (e.g. another estimator)
        return False
    plt = _pyplot()
    a, e = np.array(w.alpha_curve).T
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.semilogx(a, e, "o-", ms=3)
    ax.axvline(w.fit.alpha, color="k", ls=":", label=f"chosen α = {w.fit.alpha:.3g}")
    ax.set_xlabel("α: weight of the measured-current columns against the model columns")
    ax.set_ylabel("weighted relative error norm")
    ax.set_title(
        "IDIM-WTLS: α is chosen where the weighted error is smallest;\n"
        "a flat curve means the gains hardly depend on α",
        fontsize=10,
    )
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    ax.ticklabel_format(axis="y", useOffset=False, style="plain")
    _save(fig, path)
    return True


def plot_singular_values(result: ProcedureResult, path: Path) -> bool:
    """Singular values of the weighted WTLS matrix; False when no WTLS was run."""
    if result.wtls is None or result.wtls.fit is None:
        return False
    plt = _pyplot()
    tls = result.wtls.fit.tls
    s = tls.singular_values
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.semilogy(np.arange(1, s.size + 1), s, ".-")
    ax.semilogy([s.size - 1, s.size], s[-2:], "o", color="C3", label="the two smallest")
    ax.annotate(
        f"gap: ratio {tls.gap:.3g}",
        xy=(s.size, s[-1]),
        xytext=(0.55, 0.25),
        textcoords="axes fraction",
        arrowprops={"arrowstyle": "->", "lw": 0.8},
    )
    ax.set_xlabel("index")
    ax.set_ylabel("singular value")
    ax.set_title(
        "WTLS matrix: the gains come from the smallest singular value's vector;\n"
        "a clear gap to the next one means that vector, and the gains, are well determined",
        fontsize=10,
    )
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    _save(fig, path)
    return True


def write_plots(result: ProcedureResult, joint_names: list[str], folder: Path) -> dict[str, str]:
    """Write every plot that applies into ``folder``; returns name -> file name."""
    out = {}
    for label, t, y, yh in _series(result):
        name = f"torques_{label}.png"
        plot_torques(label, t, y, yh, joint_names, result.final.name, folder / name)
        out[f"torques_{label}"] = name
    if plot_alpha(result, folder / "alpha.png"):
        out["alpha"] = "alpha.png"
    if plot_singular_values(result, folder / "singular_values.png"):
        out["singular_values"] = "singular_values.png"
    return out
