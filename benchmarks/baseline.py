"""The previous release as a baseline in the same run (issue 19): whole-process commands of
this tree and of an earlier commit, timed side by side.

:class:`BaselineInstall` checks out REF in a git worktree in a temporary folder and installs it
into a temporary venv without the network: the venv sees the development venv's site-packages
through a ``.pth`` file (numpy, scipy, pinocchio... are shared, not reinstalled), and the
commit's own package is installed with ``pip install --no-deps --no-build-isolation --no-index``
(pip and setuptools from the development venv). The worktree is removed as soon as the package
is installed; the venv at the end.

:func:`measure` runs one command in a child process and returns its wall time, CPU time and
peak resident memory (``wait4``'s ``ru_maxrss``: the largest of the process and the children it
waited for, not their sum).

Usage from a benchmark::

    with BaselineInstall("c03ea6b") as base:
        now = measure([*current_command("drivegain"), "excite", ...])
        then = measure([*base.command("drivegain"), "excite", ...])
        print(comparison_line("excite --budget 1", now, then))

or with the scaffolding the benchmarks share: the ``--baseline-ref [REF]`` and ``--repeats``
options (:func:`add_options`), the install announced with the table header (:func:`installed`)
and one ``drivegain`` command of each tree, best of the repeats (:func:`now_and_then`)::

    with installed(args.baseline_ref, args.repeats) as base:
        now, then = now_and_then(base, ["excite", ...], ["--out", a], ["--out", b], args.repeats)
        print(comparison_line("excite --budget 1", now, then))
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from drivegain.lifecycle import Closing

REPO = Path(__file__).resolve().parents[1]
DEFAULT_REF = "c03ea6b"


@dataclass(frozen=True)
class Measure:
    """One whole-process run: wall time (s), CPU time of the process and its children (s),
    peak resident memory (MB) and exit status."""

    wall_s: float
    cpu_s: float
    peak_mb: float
    status: int


def measure(
    cmd: list[str], *, cwd: Path | None = None, env: dict[str, str] | None = None
) -> Measure:
    """Run ``cmd`` (output discarded) and measure it."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        cmd, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    assert proc.stderr is not None
    err = proc.stderr.read()  # the child may write much: read before waiting
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    proc.stderr.close()
    if proc.returncode != 0:
        tail = err.decode(errors="replace").strip().splitlines()[-3:]
        print(f"  command failed ({proc.returncode}): {' '.join(cmd)}\n  " + "\n  ".join(tail))
    return Measure(
        wall_s=wall,
        cpu_s=usage.ru_utime + usage.ru_stime,
        peak_mb=usage.ru_maxrss / 1024,
        status=proc.returncode,
    )


def best_of(cmds: list[list[str]], repeats: int) -> list[Measure]:
    """Each command ``repeats`` times, interleaved (so both see the same machine load); the
    fastest run of each by wall time."""
    runs: list[list[Measure]] = [[] for _ in cmds]
    for _ in range(repeats):
        for i, cmd in enumerate(cmds):
            runs[i].append(measure(cmd))
    return [min(r, key=lambda m: m.wall_s) for r in runs]


def current_command(script: str) -> list[str]:
    """The console script of this tree (the development venv the benchmark runs in)."""
    return [str(Path(sys.executable).with_name(script))]


def comparison_header() -> str:
    return (
        f"{'case':<40}{'now s':>8}{'base s':>8}{'ratio':>7}{'now CPU':>9}{'base CPU':>9}"
        f"{'ratio':>7}{'now MB':>8}{'base MB':>8}"
    )


def comparison_line(name: str, now: Measure, base: Measure | None) -> str:
    """One row: this tree beside the baseline; ratios = baseline / now (> 1: faster now), of
    wall time and of CPU time (the CPU time varies less with what else runs on the machine)."""
    if base is None:
        return f"{name:<40}{now.wall_s:>8.2f}{'-':>8}{'-':>7}{now.cpu_s:>9.2f}{'-':>9}" + (
            f"{'-':>7}{now.peak_mb:>8.0f}{'-':>8}"
        )
    fail = "" if now.status == 0 and base.status == 0 else "  (a run failed)"
    return (
        f"{name:<40}{now.wall_s:>8.2f}{base.wall_s:>8.2f}{base.wall_s / now.wall_s:>6.1f}x"
        f"{now.cpu_s:>9.2f}{base.cpu_s:>9.2f}{base.cpu_s / now.cpu_s:>6.1f}x"
        f"{now.peak_mb:>8.0f}{base.peak_mb:>8.0f}{fail}"
    )


class BaselineInstall(Closing):
    """REF installed in a temporary venv (a context manager; see the module docstring)."""

    def __init__(self, ref: str = DEFAULT_REF, repo: Path = REPO) -> None:
        self.ref = ref
        self.repo = repo
        self.root = Path(tempfile.mkdtemp(prefix="drivegain-baseline-"))
        self.venv = self.root / "venv"

    def __enter__(self) -> BaselineInstall:
        try:
            self._install()
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        """Remove the temporary folder (venv and all)."""
        shutil.rmtree(self.root, ignore_errors=True)

    def command(self, script: str) -> list[str]:
        """The console script as REF installed it."""
        return [str(self.venv / "bin" / script)]

    @property
    def python(self) -> Path:
        return self.venv / "bin" / "python"

    def _install(self) -> None:
        src = self.root / "src"
        t0 = time.perf_counter()
        _run(["git", "-C", str(self.repo), "worktree", "add", "--detach", str(src), self.ref])
        try:
            _run([sys.executable, "-m", "venv", "--without-pip", str(self.venv)])
            purelib = Path(
                sysconfig.get_path(
                    "purelib", vars={"base": str(self.venv), "platbase": str(self.venv)}
                )
            )
            purelib.mkdir(parents=True, exist_ok=True)
            # The development venv's package folders, after the venv's own (where REF is
            # installed), as this process sees them (cmeel's prefix for pinocchio included).
            # A path in a .pth file is only appended to sys.path: the development venv's own
            # .pth files (its editable drivegain) are not processed.
            dev = Path(sys.prefix).resolve()
            shared = [
                p
                for p in sys.path
                if p
                and Path(p).is_dir()
                and Path(p).resolve().is_relative_to(dev)
                and not Path(p).resolve().is_relative_to(self.repo.resolve() / "core")
            ]
            (purelib / "_drivegain_dev_site.pth").write_text("\n".join(shared) + "\n")
            _run(
                [
                    str(self.python),
                    "-m",
                    "pip",
                    "install",
                    "--quiet",
                    "--no-deps",
                    "--no-build-isolation",
                    "--no-index",
                    "--disable-pip-version-check",
                    str(src),
                ],
                env={**os.environ, "PIP_NO_INPUT": "1"},
            )
        finally:
            subprocess.run(
                ["git", "-C", str(self.repo), "worktree", "remove", "--force", str(src)],
                check=False,
                capture_output=True,
            )
            subprocess.run(
                ["git", "-C", str(self.repo), "worktree", "prune"], check=False, capture_output=True
            )
        self.install_s = time.perf_counter() - t0

    def check(self, package: str = "drivegain") -> str:
        """Where REF's package is imported from, in its venv (must be the venv, not the tree)."""
        out = subprocess.run(
            [str(self.python), "-c", f"import {package}; print({package}.__file__)"],
            check=True,
            capture_output=True,
            text=True,
            cwd=self.root,
        )
        return out.stdout.strip()


def add_options(parser: argparse.ArgumentParser, what: str) -> None:
    """The options of a comparison with an earlier commit: ``--baseline-ref [REF]`` (instead of
    the benchmark, ``what`` beside REF's; REF defaults to :data:`DEFAULT_REF`) and
    ``--repeats``."""
    parser.add_argument(
        "--baseline-ref",
        nargs="?",
        const=DEFAULT_REF,
        metavar="REF",
        help=f"instead: {what} beside REF's (default {DEFAULT_REF})",
    )
    parser.add_argument("--repeats", type=int, default=1, help="--baseline-ref: runs of each")


@contextmanager
def installed(ref: str, repeats: int) -> Iterator[BaselineInstall]:
    """REF installed (:class:`BaselineInstall`), announced, and the comparison table's header
    printed: the rows (:func:`comparison_line`) go inside the block."""
    print(f"installing {ref} in a temporary venv (offline)...", flush=True)
    with BaselineInstall(ref) as base:
        print(f"  done in {base.install_s:.0f} s: {base.check()}")
        print(f"best of {repeats}, interleaved; ratio = baseline / now")
        print(comparison_header())
        yield base


def now_and_then(
    base: BaselineInstall,
    args: Sequence[str],
    now_out: Sequence[str],
    base_out: Sequence[str],
    repeats: int,
) -> tuple[Measure, Measure]:
    """``drivegain ARGS`` of this tree (with ``now_out``) and of REF (with ``base_out``: the
    output options, so the two never write the same file), best of ``repeats`` interleaved."""
    now, then = best_of(
        [
            [*current_command("drivegain"), *args, *now_out],
            [*base.command("drivegain"), *args, *base_out],
        ],
        repeats,
    )
    return now, then


def _run(cmd: list[str], env: dict[str, str] | None = None) -> None:
    out = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({out.returncode}):\n{out.stderr.strip()}")
