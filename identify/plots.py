"""PNG plots of an identification (matplotlib, Agg backend: no display needed).

- ``torques_<run>.png``, one per run: measured (V·g) and computed (W·χ) joint torques per joint
  (the paper's Fig. 3) and, under each joint, their difference on its own scale,
- ``alpha.png``: the α curve of IDIM-WTLS (what the choice of α was made from),
- ``singular_values.png``: singular values of the weighted WTLS matrix and the gap that makes
  the gains well determined.

matplotlib is imported by the functions that draw, so a command that writes no plots
(``--no-plots``) never loads it; :func:`write_plots` is the single entry point. A caller that
knows early that it will plot can :func:`start_worker`: a forked process imports matplotlib
while the caller reads and fits, and draws the figures :func:`write_plots` hands it.
"""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from drivegain.identify.forked import fork_is_safe
from drivegain.identify.procedure import ProcedureResult

if TYPE_CHECKING:
    from matplotlib.axes import Axes
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
    # No bbox_inches="tight": it draws the figure twice (once to measure); the figures are
    # laid out by their constrained layout or fixed margins. Light PNG compression: 10 %
    # faster to write for 9 % more bytes.
    fig.savefig(path, dpi=110, pil_kwargs={"compress_level": 1})
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
    rms: np.ndarray | None = None,
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
    rms
        RMS of each joint's difference, N·m (from ``measured`` and ``computed`` when omitted:
        pass it when those are thinned).
    """
    plt = _pyplot()
    n = measured.shape[1]
    height = 2.3 * n
    fig = plt.figure(figsize=(10, height))
    # per joint a tall torque axis and a short difference axis with its own (smaller) scale;
    # fixed margins (inches) for the two-line axis labels, the title and the time axis: a
    # constrained layout measures every label twice and took most of the drawing time
    grid = fig.add_gridspec(
        2 * n,
        1,
        height_ratios=[3, 1.3] * n,
        left=0.8 / 10,
        right=0.99,
        top=1.0 - 0.35 / height,
        bottom=0.5 / height,
        hspace=0.12,
    )
    sl = _thin(t.size)
    if rms is None:
        diffs = measured - computed
        rms = np.sqrt(np.mean(diffs**2, axis=0)) if t.size else np.full(n, np.nan)
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
        ad = fig.add_subplot(grid[2 * j + 1], sharex=first)
        ad.plot(t[sl], diff[sl], lw=0.6, color="C3")
        ad.axhline(0.0, color="k", lw=0.5)
        ad.set_ylabel("diff.\nN·m", fontsize=8)
        ad.text(
            0.995,
            0.92,
            f"measured − computed, RMS {float(rms[j]):.3g} N·m",
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
    draw_alpha(np.array(w.alpha_curve), w.fit.alpha, path)
    return True


def draw_alpha(curve: np.ndarray, chosen: float, path: Path) -> None:
    """The α curve ((points, 2): α and the weighted relative error) with the chosen α."""
    plt = _pyplot()
    a, e = np.asarray(curve).T
    fig, ax = plt.subplots(figsize=(7, 4), layout="constrained")
    ax.semilogx(a, e, "o-", ms=3)
    ax.axvline(chosen, color="k", ls=":", label=f"chosen α = {chosen:.3g}")
    _label(
        ax,
        "α: weight of the measured-current columns against the model columns",
        "weighted relative error norm",
        "IDIM-WTLS: α is chosen where the weighted error is smallest;\n"
        "a flat curve means the gains hardly depend on α",
    )
    ax.ticklabel_format(axis="y", useOffset=False, style="plain")
    _save(fig, path)


def plot_singular_values(result: ProcedureResult, path: Path) -> bool:
    """Singular values of the weighted WTLS matrix; False when no WTLS was run."""
    if result.wtls is None or result.wtls.fit is None:
        return False
    tls = result.wtls.fit.tls
    draw_singular_values(np.asarray(tls.singular_values), float(tls.gap), path)
    return True


def draw_singular_values(s: np.ndarray, gap: float, path: Path) -> None:
    """Singular values ``s`` of the weighted WTLS matrix and the ratio of the smallest two."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4), layout="constrained")
    ax.semilogy(np.arange(1, s.size + 1), s, ".-")
    ax.semilogy([s.size - 1, s.size], s[-2:], "o", color="C3", label="the two smallest")
    ax.annotate(
        f"gap: ratio {gap:.3g}",
        xy=(s.size, s[-1]),
        xytext=(0.55, 0.25),
        textcoords="axes fraction",
        arrowprops={"arrowstyle": "->", "lw": 0.8},
    )
    _label(
        ax,
        "index",
        "singular value",
        "WTLS matrix: the gains come from the smallest singular value's vector;\n"
        "a clear gap to the next one means that vector, and the gains, are well determined",
    )
    _save(fig, path)


def _label(ax: Axes, xlabel: str, ylabel: str, title: str) -> None:
    """Axis labels, title, grid and legend of the one-panel figures (α curve, singular values)."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend()


#: prctl option: the signal a process gets when its parent dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1

#: A figure to draw: a drawing function of this module and its (small, picklable) arguments.
Job = tuple[Callable[..., None], tuple[Any, ...]]


def plot_jobs(
    result: ProcedureResult, joint_names: list[str], folder: Path
) -> tuple[list[Job], dict[str, str]]:
    """The figures that apply to ``result``, as drawing jobs, and name -> file name."""
    jobs: list[Job] = []
    out = {}
    for label, t, y, yh in _series(result):
        name = f"torques_{label}.png"
        sl = _thin(t.size)  # only the drawn points travel to a worker; RMS from every sample
        rms = np.sqrt(np.mean((y - yh) ** 2, axis=0)) if t.size else np.full(y.shape[1], np.nan)
        args = (label, t[sl], y[sl], yh[sl], list(joint_names), result.final.name, folder / name)
        jobs.append((plot_torques, (*args, rms)))
        out[f"torques_{label}"] = name
    w = result.wtls
    if w is not None and w.fit is not None and w.alpha_curve:
        jobs.append((draw_alpha, (np.array(w.alpha_curve), w.fit.alpha, folder / "alpha.png")))
        out["alpha"] = "alpha.png"
    if w is not None and w.fit is not None:
        tls = w.fit.tls
        path = folder / "singular_values.png"
        jobs.append((draw_singular_values, (np.asarray(tls.singular_values), float(tls.gap), path)))
        out["singular_values"] = "singular_values.png"
    return jobs, out


def write_plots(result: ProcedureResult, joint_names: list[str], folder: Path) -> dict[str, str]:
    """Write every plot that applies into ``folder``; returns name -> file name.

    Drawn by the worker of :func:`start_worker` when one is running, else here.
    """
    jobs, out = plot_jobs(result, joint_names, folder)
    worker = _WORKER
    if worker is not None and worker.run(jobs):
        return out
    for fn, args in jobs:
        fn(*args)
    return out


class _Worker:
    """A forked process that imports matplotlib at once, then draws the jobs it is sent."""

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("fork")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_serve, args=(child,), daemon=True)
        self.proc.start()
        child.close()

    def run(self, jobs: list[Job]) -> bool:
        """Draw ``jobs`` in the worker; False when it is gone (the caller draws them)."""
        try:
            self.conn.send(jobs)
            status = self.conn.recv()
        except (OSError, EOFError):
            return False
        # On a failure the caller draws the figures itself, which raises the error as
        # drawing in this process would (no exception has to cross the pipe).
        return bool(status == "ok")

    def stop(self) -> None:
        # Killed, not asked: it holds nothing to save, and one stopped early (an input
        # error) may still be importing matplotlib, which the caller should not wait for.
        self.conn.close()
        self.proc.kill()
        self.proc.join()


def _serve(conn: Any) -> None:
    """The worker's loop: jobs in, "ok" or "failed" out."""
    # Ctrl-C and SIGTERM are the parent's to handle (it stops the worker); the inherited
    # handler would print a traceback here.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _pyplot()
    while True:
        try:
            jobs = conn.recv()
        except (EOFError, OSError):
            return
        try:
            ok = draw_split(jobs)
        except Exception:  # the caller redraws in its own process and reports the error
            ok = False
        conn.send("ok" if ok else "failed")


def _die_with_parent(parent: int) -> None:
    """Have the kernel kill this process when its parent dies (Linux ``PR_SET_PDEATHSIG``).

    Why: the worker is killed, not asked, when an identification stops early (an error,
    SIGTERM); a child left drawing would write a figure into a report folder being removed.
    """
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL))
    except (OSError, AttributeError):  # not Linux: the child ends with its figure
        return
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)


def draw_split(jobs: list[Job]) -> bool:
    """Draw ``jobs``, every other one in a child forked from here; whether all were drawn.

    Why: the figures are drawn at the end of an identification, when nothing else runs; a
    child of this process has matplotlib imported already, so on two CPUs the two torque
    figures take the time of one. Without a safe fork (:func:`.forked.fork_is_safe`), or
    with one job, all are drawn here. Raises what a job drawn here raises.
    """
    theirs, mine = jobs[0::2], jobs[1::2]
    if not mine or not fork_is_safe() or len(os.sched_getaffinity(0)) < 2:
        theirs, mine = [], jobs
    parent = os.getpid()
    pid = os.fork() if theirs else 0
    if theirs and pid == 0:  # the child: its share, then out without any cleanup of ours
        code = 1
        try:
            _die_with_parent(parent)
            for fn, args in theirs:
                fn(*args)
            code = 0
        finally:
            os._exit(code)
    try:
        for fn, args in mine:
            fn(*args)
    finally:
        status = os.waitpid(pid, 0)[1] if theirs else 0
    return os.waitstatus_to_exitcode(status) == 0


_WORKER: _Worker | None = None


def start_worker() -> None:
    """Fork the plotting worker now.

    A no-op when one runs, when fork is unavailable, or when this process runs other threads
    (a fork copies their locks in whatever state they are: the worker could deadlock).
    """
    global _WORKER
    if _WORKER is None and fork_is_safe():
        _WORKER = _Worker()


def stop_worker() -> None:
    """End the plotting worker, if any."""
    global _WORKER
    worker, _WORKER = _WORKER, None
    if worker is not None:
        worker.stop()
