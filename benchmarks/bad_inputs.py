"""Every bad input a user met, replayed: one line on stderr, exit status 2, nothing written.

Usage: ``python benchmarks/bad_inputs.py [--keep DIR]``

Each case runs the installed ``drivegain`` command in a fresh folder holding good copies of the
shipped files and the case's bad file. A case passes when the command exits with status 2,
prints exactly one line on stderr and no traceback, and every file in the folder (and the
folders the case names) is byte for byte what it was. Prints one line per case and the summary
``N tried, N one-line errors, 0 tracebacks, 0 files changed``; exits 1 if any case failed.

This is a replay of a list, not a timed benchmark: it measures correctness of the refusals.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivegain.config import resource_path
from drivegain.formats.log import RunMetadata
from drivegain.formats.logwriter import write_run

#: A folder no one may create files in, root included (the probe checks it).
READ_ONLY = Path("/sys/fs")


@dataclass(frozen=True)
class Case:
    """One bad input: a name, how to prepare the folder, and the command's arguments."""

    name: str
    args: Callable[[Path], list[str]]
    prepare: Callable[[Path], None] = lambda d: None


def _replace(src: str, dst: str, old: str, new: str) -> Callable[[Path], None]:
    def prepare(d: Path) -> None:
        text = resource_path(src).read_text()
        assert old in text, (src, old)
        (d / dst).write_text(text.replace(old, new, 1))

    return prepare


def _log(name: str, position_value: float | None = None) -> Callable[[Path], None]:
    def prepare(d: Path) -> None:
        n = 400
        rng = np.random.default_rng(0)
        pos = rng.normal(size=(n, 6)) * 0.1
        if position_value is not None:
            pos[10, 2] = position_value
        meta = RunMetadata(
            robot="Staubli TX-40",
            run="unloaded",
            payload="none",
            joint_names=["j1", "j2", "j3", "j4", "j5", "j6"],
            sync_period_s=0.004,
            started_at="2026-01-01T00:00:00.000Z",
            drivegain_version="0",
        )
        write_run(d / name, meta, np.arange(n) * 0.004, pos, rng.normal(size=(n, 6)))

    return prepare


def _corrupt_length(d: Path) -> None:
    _log("good.mcap")(d)
    data = bytearray((d / "good.mcap").read_bytes())
    start = data.index(b"\x06", 8)  # the first chunk record (opcode 0x06) after the header
    data[start + 1 : start + 9] = (2**31).to_bytes(8, "little")
    (d / "corrupt.mcap").write_bytes(bytes(data))
    (d / "good.mcap").unlink()


def _csv(d: Path) -> None:
    (d / "p.csv").write_text("\n".join(",".join(["0.1"] * 6) for _ in range(50)) + "\n")


def _existing_log(d: Path) -> None:
    _csv(d)
    (d / "recorded.mcap").write_bytes(b"a recorded log that must survive")


def _big_trajectory(d: Path) -> None:
    doc = json.loads(resource_path("tx40-excitation.json").read_text())
    doc["periods"] = 1_000_000_000
    (d / "traj.json").write_text(json.dumps(doc))


def _node7_fault(d: Path) -> None:
    # the shipped config's relative paths would not resolve from the case folder: make them
    # absolute, so that the only thing wrong is the node
    text = resource_path("acquire-sim.toml").read_text()
    for rel in ("tx40.toml", "sim/tx40-truth.toml"):
        assert f'"{rel}"' in text, rel
        text = text.replace(f'"{rel}"', f'"{resource_path(rel)}"', 1)
    text += '\n[[simulation.fault]]\nkind = "emcy"\nnode = 7\nat_s = 1.0\n'
    (d / "acq.toml").write_text(text)


ROBOT = str(resource_path("tx40.toml"))
ACQ = str(resource_path("acquire-sim.toml"))
TRAJ = str(resource_path("tx40-excitation.json"))
CONV = ["convert", "csv", "--positions", "p.csv", "--currents", "p.csv", "--robot", ROBOT]

CASES = [
    Case(
        "acquire --payload with mass 1e300",
        lambda d: [
            "acquire",
            "--config",
            ACQ,
            "--trajectory",
            TRAJ,
            "--out",
            "r.mcap",
            "--payload",
            "p.toml",
        ],
        _replace("payloads/calibrated-4590g.toml", "p.toml", "mass = 4.59", "mass = 1e300"),
    ),
    Case(
        "acquire with 10^9 periods",
        lambda d: ["acquire", "--config", ACQ, "--trajectory", "traj.json", "--out", "r.mcap"],
        _big_trajectory,
    ),
    Case(
        "acquisition TOML with a fault on node 7",
        lambda d: ["acquire", "--config", "acq.toml", "--trajectory", TRAJ, "--out", "r.mcap"],
        _node7_fault,
    ),
    Case(
        "model info with velocity_limit 1e308",
        lambda d: ["model", "info", "--robot", "r.toml"],
        _replace(
            "tx40.toml", "r.toml", "velocity_limit = 5.009094953223726", "velocity_limit = 1e308"
        ),
    ),
    Case("model info --samples 0", lambda d: ["model", "info", "--robot", ROBOT, "--samples", "0"]),
    Case(
        "model info --samples -5", lambda d: ["model", "info", "--robot", ROBOT, "--samples", "-5"]
    ),
    Case(
        "excite --base-frequency 1e308",
        lambda d: ["excite", "--robot", ROBOT, "--out", "t.json", "--base-frequency", "1e308"],
    ),
    Case(
        "excite --harmonics 10000",
        lambda d: ["excite", "--robot", ROBOT, "--out", "t.json", "--harmonics", "10000"],
    ),
    Case(
        "excite --out in a read-only folder",
        lambda d: ["excite", "--robot", ROBOT, "--out", str(READ_ONLY / "t.json")],
    ),
    Case(
        "convert csv --rate 1e-300", lambda d: [*CONV, "--rate", "1e-300", "--out", "r.mcap"], _csv
    ),
    Case("convert csv --out a folder", lambda d: [*CONV, "--rate", "100", "--out", "."], _csv),
    Case(
        "convert csv --out an existing log",
        lambda d: [*CONV, "--rate", "100", "--out", "recorded.mcap"],
        _existing_log,
    ),
    Case("convert csv --out x.txt", lambda d: [*CONV, "--rate", "100", "--out", "x.txt"], _csv),
    Case("demo --out a read-only folder", lambda d: ["demo", "--out", str(READ_ONLY / "demo")]),
    Case(
        "demo --out an existing file", lambda d: ["demo", "--out", "recorded.mcap"], _existing_log
    ),
    Case(
        "identify --out a read-only folder",
        lambda d: [
            "identify",
            "--robot",
            ROBOT,
            "--unloaded",
            "a.mcap",
            "--out",
            str(READ_ONLY / "report"),
        ],
        _log("a.mcap"),
    ),
    Case(
        "identify a log with one position 1e300",
        lambda d: ["identify", "--robot", ROBOT, "--unloaded", "a.mcap", "--out", "rep"],
        _log("a.mcap", 1e300),
    ),
    Case(
        "identify a log whose first chunk length is 2^31",
        lambda d: ["identify", "--robot", ROBOT, "--unloaded", "corrupt.mcap", "--out", "rep"],
        _corrupt_length,
    ),
]


def _snapshot(folder: Path) -> dict[str, str]:
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            out[str(p.relative_to(folder))] = hashlib.sha256(p.read_bytes()).hexdigest()
        else:
            out[str(p.relative_to(folder))] = "dir"
    return out


def run_case(case: Case, work: Path, drivegain: list[str]) -> tuple[bool, str]:
    """Run one case in ``work``; (passed, one-line verdict)."""
    case.prepare(work)
    before = _snapshot(work)
    ro_before = sorted(os.listdir(READ_ONLY))
    t0 = time.perf_counter()
    try:
        res = subprocess.run(
            [*drivegain, *case.args(work)],
            cwd=work,
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
    except subprocess.TimeoutExpired:
        return False, "no answer within 120 s"
    dt = time.perf_counter() - t0
    lines = res.stderr.strip().splitlines()
    problems = []
    if res.returncode != 2:
        problems.append(f"exit {res.returncode}")
    if "Traceback" in res.stderr:
        problems.append("traceback")
    if len(lines) != 1:
        problems.append(f"{len(lines)} stderr lines")
    if _snapshot(work) != before or sorted(os.listdir(READ_ONLY)) != ro_before:
        problems.append("files changed")
    first = lines[-1] if lines else "(nothing on stderr)"
    verdict = f"{dt:5.1f} s  {first}" if not problems else f"{', '.join(problems)}: {first}"
    return not problems, verdict


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keep", type=Path, help="keep the case folders here")
    args = parser.parse_args()
    exe = shutil.which("drivegain", path=str(Path(sys.executable).parent)) or "drivegain"
    drivegain = [exe]
    root = Path(tempfile.mkdtemp(prefix="drivegain-bad-")) if args.keep is None else args.keep
    counts = {"tried": 0, "one_line": 0, "tracebacks": 0, "changed": 0}
    failed = 0
    for i, case in enumerate(CASES):
        work = root / f"case{i:02d}"
        work.mkdir(parents=True)
        ok, verdict = run_case(case, work, drivegain)
        counts["tried"] += 1
        counts["one_line"] += ok or not any(
            bad in verdict for bad in ("stderr lines", "exit", "no answer")
        )
        counts["tracebacks"] += "traceback" in verdict and not ok
        counts["changed"] += "files changed" in verdict and not ok
        failed += not ok
        print(f"{'ok ' if ok else 'BAD'} {case.name}: {verdict}")
    if args.keep is None:
        shutil.rmtree(root, ignore_errors=True)
    print(
        f"{counts['tried']} tried, {counts['one_line']} one-line errors, "
        f"{counts['tracebacks']} tracebacks, {counts['changed']} files changed"
    )
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
