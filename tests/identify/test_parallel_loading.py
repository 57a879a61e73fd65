"""Runs read and prepared in worker processes (long logs): the same report as one after the
other, errors named as before, a worker that dies reported by run."""

from __future__ import annotations

import json
import multiprocessing
import os
from pathlib import Path

import pytest
from mcap.reader import make_reader

from drivegain.cli import main
from drivegain.config import resource_path
from drivegain.errors import IdentificationError
from drivegain.identify import loading
from drivegain.identify.pipeline import IdentifyRequest, run_identify

ROBOT = resource_path("tx40.toml")
PAYLOADS = {"b": "payloads/calibrated-4590g.toml", "c": "payloads/validation-1686g.toml"}


@pytest.fixture(scope="module")
def logs(run_logs, tmp_path_factory) -> dict[str, Path]:
    """Runs a (unloaded), b (calibrated payload) and c (validation payload), 20 s each."""
    seeds = {"a": 11, "b": 12, "c": 13}
    return run_logs(tmp_path_factory.mktemp("logs"), seeds, seconds=20.0)


def _argv(logs: dict[str, Path], out: Path, unloaded: Path | None = None) -> list[str]:
    return [
        "identify",
        *("--robot", str(ROBOT), "--unloaded", str(unloaded or logs["a"])),
        *("--loaded", str(logs["b"]), "--payload", str(resource_path(PAYLOADS["b"]))),
        *("--validate", str(logs["c"]), "--validate-payload", str(resource_path(PAYLOADS["c"]))),
        *("--no-plots", "--out", str(out)),
    ]


def _ignore_suite_threads(monkeypatch: pytest.MonkeyPatch) -> None:
    """Threads left by other tests of the suite (daemon threads of buses, notifiers) would make
    the fork-safety rule say no; the workers here touch no lock of theirs."""
    monkeypatch.setattr(loading, "fork_is_safe", lambda: _CAN_FORK)


#: A fork is possible here at all.
_CAN_FORK = "fork" in multiprocessing.get_all_start_methods() and len(os.sched_getaffinity(0)) > 1


@pytest.fixture
def parallel(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any log size takes the worker processes (where this machine can fork at all)."""
    monkeypatch.setattr(loading, "PARALLEL_BYTES", 0)
    _ignore_suite_threads(monkeypatch)
    specs = [(Path(__file__), "a", None), (Path(__file__), "b", None)]
    if len(os.sched_getaffinity(0)) < 2 or loading._worker_count(specs) < 2:
        pytest.skip("one CPU, no fork or other threads running: the runs are read in turn")


def _without_times(report: dict) -> dict:
    report = dict(report)
    report.pop("files", None)
    return report


def test_workers_give_the_report_of_the_runs_read_in_turn(
    logs: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert main(_argv(logs, tmp_path / "in-turn")) == 0
    monkeypatch.setattr(loading, "PARALLEL_BYTES", 0)
    _ignore_suite_threads(monkeypatch)
    if loading._worker_count([(logs["a"], "a", None), (logs["b"], "b", None)]) < 2:
        pytest.skip("one CPU, no fork or other threads running: the runs are read in turn")
    calls = []
    real = loading._in_workers
    monkeypatch.setattr(loading, "_in_workers", lambda *a: calls.append(1) or real(*a))
    assert main(_argv(logs, tmp_path / "workers")) == 0
    a = json.loads((tmp_path / "in-turn" / "report.json").read_text())
    b = json.loads((tmp_path / "workers" / "report.json").read_text())
    # once, and once more where the Coulomb sign's two preparations were compared (signchoice)
    chose = any("chosen by the runs' likelihood" in n for r in b["runs"] for n in r["notes"])
    assert calls == [1, 1] if chose else calls == [1]
    assert _without_times(a) == _without_times(b)  # every number, to the last bit
    assert [r["label"] for r in b["runs"]] == ["unloaded", "loaded", "validation"]


def _corrupt(log: Path, bad: Path) -> Path:
    """``log`` with 64 bytes overwritten inside a compressed chunk in its middle, as ``bad``
    (its header and summary still read)."""
    data = bytearray(log.read_bytes())
    with log.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    chunk = summary.chunk_indexes[len(summary.chunk_indexes) // 2]
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[middle : middle + 64] = b"\xff" * 64
    bad.write_bytes(bytes(data))
    return bad


@pytest.mark.parametrize("every_round", [False, True], ids=["as-ready", "all-ready"])
def test_a_corrupt_log_read_by_a_worker_is_named_and_nothing_is_written(
    logs: dict[str, Path],
    tmp_path: Path,
    parallel: None,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    every_round: bool,
) -> None:
    """One line naming the file, nothing written. ``all-ready``: every round of the reader
    sees every worker ready (each waited for in turn, so it does not depend on timing), so run
    b's worker is ready in the round where run a's reports its error; it is dropped, not read
    after it (that once ended in an internal KeyError)."""
    if every_round:
        real = loading.wait

        def all_ready(conns, timeout=None):
            for c in conns:
                real([c])
            return list(conns)

        monkeypatch.setattr(loading, "wait", all_ready)
    bad = _corrupt(logs["a"], tmp_path / "bad.mcap")
    out = tmp_path / "out"
    assert main(_argv(logs, out, unloaded=bad)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0] and "corrupt" in err[0], err
    assert not out.exists()


def test_a_worker_that_dies_is_reported_by_run(
    logs: dict[str, Path], tmp_path: Path, parallel: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    def die(model, columns, spec, req, steps):  # runs in the forked worker only
        if spec[1] == "loaded":
            os._exit(3)
        return real(model, columns, spec, req, steps)

    real = loading._load_one
    monkeypatch.setattr(loading, "_load_one", die)
    req = IdentifyRequest(
        robot=ROBOT,
        unloaded=logs["a"],
        loaded=logs["b"],
        payload=resource_path(PAYLOADS["b"]),
        out=tmp_path / "out",
        progress=False,
        plots=False,
    )
    with pytest.raises(IdentificationError, match=r"run loaded \(.*b\.mcap\): the process"):
        run_identify(req)
    assert not (tmp_path / "out").exists()
