"""``drivegain ctl``: the daemon's client against a running daemon on the simulated cell."""

from __future__ import annotations

import json
import logging
import socket
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from drivegain.acquire.config import load_acquisition_config
from drivegain.acquire.daemon import Daemon
from drivegain.cli import main
from drivegain.formats.logreader import read_run


class _Quiet:
    """A systemd notifier that says nothing."""

    def notify(self, state: str) -> None:
        pass


def _ready(records: list[logging.LogRecord]) -> list[str]:
    return [r.getMessage() for r in records if getattr(r, "event", None) == "ready"]


def ctl(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    """``drivegain ctl ARGV``: exit status, stdout, stderr."""
    code = main(["ctl", *argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def served(
    tmp_path: Path,
    make_config: Callable[..., Path],
    daemon_kit: SimpleNamespace,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> Iterator[tuple[Daemon, Path]]:
    """A daemon on the lockstep cell whose ``[daemon] socket`` is relative (to ``tmp_path``)."""
    monkeypatch.chdir(tmp_path)
    caplog.set_level(logging.INFO, logger="drivegain.acquire.daemon")
    cfg_path = make_config(daemon=f'socket = "ctl.sock"\noutput_dir = "{tmp_path / "runs"}"')
    d = Daemon(load_acquisition_config(cfg_path), notifier=_Quiet())
    with daemon_kit.serve(d, join_s=30) as th:
        daemon_kit.wait(lambda: d.rig is not None and d.rig.master is not None, what="the boot")
        daemon_kit.wait(lambda: _ready(caplog.records), what="the ready line")
        yield d, cfg_path
    assert not th.is_alive()


def test_status_run_stop_through_the_client(
    served: tuple[Daemon, Path],
    daemon_kit: SimpleNamespace,
    tmp_path: Path,
    short_trajectory: Path,
    long_trajectory: Path,
    capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    _, cfg = served
    sock = tmp_path / "ctl.sock"
    # the daemon said where its socket is and how to talk to it
    ready = _ready(caplog.get_records("setup"))
    assert ready and f"drivegain ctl status --socket {sock}" in ready[0], ready

    code, out, err = ctl(capsys, "status", "--config", str(cfg))  # the socket from the TOML
    assert code == 0 and out.startswith("idle: 0 runs") and "lockstep clock" in out, (out, err)
    code, out, _ = ctl(capsys, "status", "--socket", str(sock), "--json")
    status = json.loads(out)
    assert code == 0 and status["ok"] and status["state"] == "idle" and status["runs"] == 0

    # a run to its end; a relative trajectory is made absolute for the daemon
    rel = Path(short_trajectory.parent.name) / short_trajectory.name
    (tmp_path / rel.parent).symlink_to(short_trajectory.parent)
    code, out, err = ctl(
        capsys, "run", "--socket", "ctl.sock", "--trajectory", str(rel), "--label", "a", "--wait"
    )
    assert code == 0, err
    started, ended = out.splitlines()
    assert started.startswith("started a (") and ended.startswith("a finished, ")
    path = ended.rsplit(" -> ", 1)[1]
    assert Path(path).parent == tmp_path / "runs"
    assert read_run(path).meta["run"] == "a"

    # a long run, stopped by the client
    code, out, err = ctl(
        capsys, "run", "--socket", str(sock), "--trajectory", str(long_trajectory), "--json"
    )
    reply = json.loads(out)
    assert code == 0 and reply["ok"] and reply["label"] == "unloaded", err
    code, out, _ = ctl(capsys, "run", "--socket", str(sock), "--trajectory", str(long_trajectory))
    assert code == 1 and out == ""  # one run at a time: the daemon's error, exit status 1
    code, out, _ = ctl(capsys, "status", "--socket", str(sock))
    assert code == 0 and out.startswith("running: 1 runs") and "run unloaded:" in out, out
    code, out, err = ctl(capsys, "stop", "--socket", str(sock))
    assert code == 0 and out == "stopping unloaded\n", err
    status = daemon_kit.wait(
        lambda: (
            (s := json.loads(ctl(capsys, "status", "--socket", str(sock), "--json")[1]))["state"]
            == "idle"
            and s
        ),
        what="idle",
    )
    assert status["last_run"]["state"] == "stopped"
    assert status["last_run"]["stop_reason"] == "stop request"

    # the daemon's error: one line on stderr and exit status 1, or the raw reply with --json
    code, out, err = ctl(capsys, "stop", "--socket", str(sock))
    assert code == 1 and out == "" and err == "drivegain: error: no run in progress\n"
    code, out, err = ctl(capsys, "stop", "--socket", str(sock), "--json")
    assert code == 1 and json.loads(out) == {"ok": False, "error": "no run in progress"}


def test_bad_input_is_one_line_naming_the_path(
    tmp_path: Path,
    make_config: Callable[..., Path],
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    plain = tmp_path / "plain.txt"
    plain.write_text("not a socket")
    stale = tmp_path / "stale.sock"
    bound = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    bound.bind(str(stale))  # bound, never listening: what a killed daemon leaves
    no_daemon = make_config()
    cases = [
        ([], "no daemon socket: give --socket PATH"),
        (["--socket", str(tmp_path / "missing.sock")], f"{tmp_path / 'missing.sock'}: no such"),
        (["--socket", str(plain)], f"{plain}: not a socket"),
        (["--socket", str(stale)], f"{stale}: nobody listens on it"),
        (["--config", str(no_daemon)], f"{no_daemon}: no [daemon] table"),
        (["--config", str(tmp_path / "nope.toml")], "nope.toml"),
    ]
    try:
        for argv, fragment in cases:
            code, out, err = ctl(capsys, "status", *argv)
            assert code == 2 and out == "", (argv, out, err)
            assert fragment in err and err.count("\n") == 1, (argv, err)

        def denied(self: socket.socket, address: Any) -> None:
            raise PermissionError(13, "Permission denied")

        # (as root a 0600 socket of another user is reachable: the refusal is simulated)
        monkeypatch.setattr(socket.socket, "connect", denied)
        code, out, err = ctl(capsys, "stop", "--socket", str(stale))
        assert code == 2 and err == f"drivegain: error: {stale}: permission denied\n"
    finally:
        bound.close()
    # a run without its trajectory is refused by the parser
    code, _, err = ctl(capsys, "run", "--socket", str(stale))
    assert code == 2 and "--trajectory" in err and err.count("\n") == 1
