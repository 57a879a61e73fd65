"""``drivegain batch`` on a Dask LocalCluster of 2 worker processes: 6 simulated robots × 2
campaigns, two of them changed in the second; a worker is killed mid-batch.

The cluster is started by the test (processes, not threads) and reached through its scheduler
address, as ``--scheduler tcp://HOST:PORT`` does; the default local cluster runs in
``benchmarks/bench_batch.py``. All the Dask work happens in the module fixture: the per-test
thread-leak check then sees none of Dask's threads.
"""

from __future__ import annotations

import json
import os
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from drivegain.cli import main
from drivegain.fleet.campaign import load_batch, load_campaign
from drivegain.fleet.drift import FleetOutputs, compute_drift, write_fleet_outputs
from drivegain.fleet.engine import BatchOutcome, EngineOptions, quiet_dask, run_batch
from drivegain.fleet.simfleet import Change, write_fleet
from drivegain.fleet.task import TaskResult

ROBOTS = [f"cell{i}-r{i}" for i in range(1, 7)]
CAMPAIGNS = [("2026-05", "2026-05-04"), ("2026-06", "2026-06-01")]
CHANGES = [
    Change("cell2-r2", "2026-06", "gain", 3, 1.03),
    Change("cell5-r5", "2026-06", "viscous", 2, 1.20),
]


@dataclass
class Run:
    campaign: Path
    out: str
    outcome: BatchOutcome
    fleet: FleetOutputs
    killed: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Run:
    from distributed import LocalCluster

    folder = tmp_path_factory.mktemp("fleet")
    campaign = write_fleet(folder, ROBOTS, CAMPAIGNS, CHANGES, batch={"identify_plots": False})
    batch = load_campaign(str(campaign))
    killed: dict[str, Any] = {}

    def kill_one(result: TaskResult, client: Any) -> None:
        """After the first result: SIGKILL a worker process that is running a task."""
        if killed:
            return
        busy = {
            w: [k for k in keys if not k.endswith(result.fingerprint)]
            for w, keys in client.processing().items()
        }
        busy = {w: keys for w, keys in busy.items() if keys}
        if not busy:
            return
        address = sorted(busy)[0]
        pid = client.run(os.getpid, workers=[address])[address]
        killed.update(address=address, pid=pid, keys=busy[address])
        os.kill(pid, signal.SIGKILL)

    start = time.perf_counter()
    with quiet_dask():
        with LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
        ) as cluster:
            engine = EngineOptions(scheduler=cluster.scheduler_address, progress=False)
            outcome = run_batch(batch, engine, on_result=kill_one)
    fleet = write_fleet_outputs(batch.options.out, batch.options.threshold)
    return Run(
        campaign=campaign,
        out=batch.options.out,
        outcome=outcome,
        fleet=fleet,
        killed=killed,
        seconds=time.perf_counter() - start,
    )


def test_exactly_the_two_changes_are_flagged(run: Run) -> None:
    flagged = {(d.robot_id, d.parameter) for d in run.fleet.drift.flagged}
    assert flagged == {("cell2-r2", "gain_j3"), ("cell5-r5", "Fv2")}
    by = {(d.robot_id, d.parameter): d for d in run.fleet.drift.flagged}
    assert by["cell2-r2", "gain_j3"].change_percent == pytest.approx(3.0, abs=0.2)
    assert by["cell5-r5", "Fv2"].change_percent == pytest.approx(20.0, abs=0.5)
    assert all(d.baseline == "2026-05" and d.campaign == "2026-06" for d in by.values())
    # Every robot compared, gains and friction alike, and the unchanged ones stay well inside.
    compared = run.fleet.drift.rows
    assert {d.robot_id for d in compared} == set(ROBOTS)
    assert len(compared) == 6 * (6 + 14)  # gains, Fv1-6, Fc1-6, fvm6, fcm6
    quiet = [abs(d.z) for d in compared if (d.robot_id, d.parameter) not in by]
    assert max(quiet) < run.fleet.drift.threshold


def test_a_killed_worker_loses_no_result(run: Run) -> None:
    assert run.killed, "no worker was busy when the first result came in"
    out = run.outcome
    assert out.computed == 12 and out.skipped == 0 and out.failed == 0, out.errors
    assert [r.status for r in out.results] == ["ok"] * 12
    for r in out.results:
        folder = Path(run.out) / "tasks" / r.task["campaign"] / r.task["robot_id"]
        doc = json.loads((folder / "result.json").read_text())
        assert doc["status"] == "ok" and doc["report"]["gains"]
        assert (folder / "report" / "report.json").is_file()
    # The tasks the dead worker held (running or queued) all have a result. The one it was
    # running may have finished between the look at its queue and the kill; the others were
    # run again, on the live worker.
    lost = [r for r in out.results if any(k.endswith(r.fingerprint) for k in run.killed["keys"])]
    assert lost and all(r.ok for r in lost)
    assert any(r.worker != run.killed["address"] for r in lost)
    print(f"batch of 12 with a worker killed: {run.seconds:.1f} s")


def test_rerun_skips_what_is_done(run: Run) -> None:
    again = run_batch(load_campaign(str(run.campaign)), EngineOptions(progress=False))
    assert again.computed == 0 and again.skipped == 12 and again.workers == 0
    assert [r.fingerprint for r in again.results] == [r.fingerprint for r in run.outcome.results]


def test_fleet_table_and_drift_files(run: Run) -> None:
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    out = Path(run.out)
    table = pq.read_table(out / "fleet.parquet")
    assert table.num_rows == 12
    names = table.column_names
    assert names[:4] == ["robot_id", "campaign", "date", "status"]
    for col in ("gain_j1", "gain_j1_std", "Fv2", "Fv2_std", "Fc6", "fvm6", "residual_relative"):
        assert col in names
    assert "warnings" in names
    rows = table.to_pylist()
    assert {(r["robot_id"], r["date"]) for r in rows} == {
        (rid, d) for rid in ROBOTS for _, d in CAMPAIGNS
    }
    assert all(0 < r["gain_j3_std"] < 0.01 * abs(r["gain_j3"]) for r in rows)
    assert pcsv.read_csv(out / "fleet.csv").num_rows == 12
    assert pq.read_table(out / "drift.parquet").num_rows == 6 * 20
    doc = json.loads((out / "drift.json").read_text())
    assert len(doc["flagged"]) == 2 and doc["threshold_sigma"] == 5.0
    for rid in ROBOTS:
        assert (out / "drift" / f"{rid}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(out.rglob("*.part"))  # every file moved into place


def test_folder_of_logs_gives_the_same_tasks(run: Run) -> None:
    from_file = load_campaign(str(run.campaign))
    logs = load_batch(
        str(run.campaign.parent / "logs"),
        out=str(run.campaign.parent / "other"),
        robot="tx40",
        payload=from_file.tasks[0].payload,
    )
    key = lambda t: (t.robot_id, t.campaign, t.date, Path(t.unloaded).name)  # noqa: E731
    assert sorted(map(key, logs.tasks)) == sorted(map(key, from_file.tasks))


def test_drift_against_a_named_baseline_and_threshold() -> None:
    rows = [
        {"robot_id": "a", "campaign": c, "date": d, "status": "ok", "g": v, "g_std": 0.1}
        for c, d, v in (("x", "2026-01-01", 1.0), ("y", "2026-02-01", 1.5), ("z", "2026-03-01", 2))
    ]
    rep = compute_drift(rows, threshold=3.0)
    assert rep.baselines == {"a": "x"}
    assert [round(d.z, 6) for d in rep.rows] == [round(0.5 / 0.1 / 2**0.5, 6), round(7.071068, 6)]
    assert [d.flagged for d in rep.rows] == [True, True]
    rep = compute_drift(rows, threshold=3.0, baseline="y")
    assert [(d.campaign, d.flagged) for d in rep.rows] == [("x", True), ("z", True)]
    rep = compute_drift(rows, threshold=10.0, baseline="nope")
    assert rep.rows == [] and "no successful identification" in rep.notes[0]


def test_bad_campaign_files_exit_2_naming_file_and_key(tmp_path, capsys) -> None:
    bad = tmp_path / "c.toml"
    bad.write_text('[batch]\nthreshhold = 3\n[[campaign]]\nname = "a"\ndate = 2026-01-01\n')
    assert main(["batch", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(bad) in err and "threshhold" in err
    bad.write_text('[[campaign]]\nname = "a b"\ndate = 2026-01-01\n')
    assert main(["batch", str(bad)]) == 2
    assert "campaign[0].name" in capsys.readouterr().err
    assert main(["batch", str(tmp_path / "missing.toml")]) == 2
    assert "file not found" in capsys.readouterr().err
    assert main(["batch", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "no .mcap log found" in capsys.readouterr().err
    assert main(["batch", str(bad), "--threshold", "0"]) == 2


def test_a_task_run_again_removes_what_a_killed_worker_left(tmp_path) -> None:
    """Temporary files of an interrupted write go; whole files and other names stay."""
    from drivegain.fleet import storage

    folder = tmp_path / "tasks" / "2026-05" / "cell1-r1"
    (folder / "report").mkdir(parents=True)
    stale = [folder / ".result.json.0a1b.part", folder / "report" / ".report.md.9f.part"]
    keep = [folder / "report" / "report.md", folder / "notes.part"]
    for f in stale + keep:
        f.write_bytes(b"x")
    removed = storage.remove_stale_parts(str(folder))
    assert sorted(Path(p).name for p in removed) == sorted(f.name for f in stale)
    assert not any(f.exists() for f in stale) and all(f.exists() for f in keep)
    assert storage.remove_stale_parts(str(tmp_path / "nothing-here")) == []
