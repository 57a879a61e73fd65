"""Child process for the crash test: writes a run, flushing every 200 cycles, until killed.

Usage: python killed_writer.py OUT.mcap. Prints ``flushed K`` after each flush (K messages on
disk). Stops by itself after 100 000 cycles so a test that fails to kill it leaves no runaway.
Values are a function of the cycle index only (see :func:`expected`), so the parent can check
every recovered message.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from drivegain.formats.log import RunMetadata
from drivegain.formats.logwriter import LogWriter

N_JOINTS = 6
PERIOD_S = 0.004
FLUSH_EVERY = 200


def expected(cycle: np.ndarray) -> dict[str, np.ndarray]:
    """The values written at these cycles."""
    c = np.asarray(cycle, dtype=float)[:, None]
    j = np.arange(N_JOINTS)[None, :]
    return {
        "position": np.sin(0.01 * c + j),
        "current_reference": np.cos(0.003 * c * (j + 1)) * (j + 1),
        "current": 0.5 * np.cos(0.003 * c * (j + 1)),
        "setpoint": np.sin(0.01 * c + j) + 1e-3,
    }


def main(out: Path) -> None:
    meta = RunMetadata(
        robot="test arm",
        run="crash",
        payload="none",
        joint_names=[f"j{i + 1}" for i in range(N_JOINTS)],
        sync_period_s=PERIOD_S,
        started_at="2026-01-01T00:00:00.000Z",
    )
    writer = LogWriter(out, meta, [("robot.toml", "application/toml", b"[robot]\n")])
    for cycle in range(100_000):
        v = expected(np.array([cycle]))
        writer.write_joint_state(
            cycle=cycle,
            t=cycle * PERIOD_S,
            log_time_ns=1_000_000_000 + cycle * 4_000_000,
            position=v["position"][0],
            current_reference=v["current_reference"][0],
            current=v["current"][0],
            setpoint=v["setpoint"][0],
        )
        writer.write_raw(
            cycle=cycle, log_time_ns=1_000_000_000 + cycle * 4_000_000, raw={"1": [cycle]}
        )
        if (cycle + 1) % FLUSH_EVERY == 0:
            writer.flush()
            print(f"flushed {cycle + 1}", flush=True)
    writer.finish()


if __name__ == "__main__":
    main(Path(sys.argv[1]))
