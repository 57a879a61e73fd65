"""The terminal: log lines above a live progress bar, no wrapping at 80 columns when piped."""

from __future__ import annotations

import io
import logging
import re
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager

from drivegain import console as con

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


class _Tty(io.StringIO):
    """A stream that says it is a terminal."""

    def isatty(self) -> bool:
        return True


@contextmanager
def _bare_root() -> Iterator[logging.Logger]:
    """The root logger without handlers, as in a fresh process (pytest adds its capture
    handlers around each test phase, so this runs inside the test body)."""
    root = logging.getLogger()
    saved, level = list(root.handlers), root.level
    for h in saved:
        root.removeHandler(h)
    try:
        yield root
    finally:
        for h in list(root.handlers):
            root.removeHandler(h)
        for h in saved:
            root.addHandler(h)
        root.setLevel(level)


def _screen_lines(raw: str) -> list[str]:
    """What a terminal shows, line by line, roughly: escape codes dropped, \\r starts over."""
    out = []
    for line in raw.split("\n"):
        out.append(ANSI.sub("", line).split("\r")[-1])
    return out


def test_log_lines_go_above_a_live_progress_bar(monkeypatch) -> None:
    from rich.logging import RichHandler
    from rich.progress import BarColumn, Progress, TextColumn

    tty = _Tty()
    monkeypatch.setattr(sys, "stderr", tty)
    monkeypatch.setenv("COLUMNS", "100")
    with _bare_root():
        handler = con.install_logging()
        assert isinstance(handler, RichHandler) and handler.console is con.console(stderr=True)
        bar = Progress(TextColumn("working"), BarColumn(), console=con.console(stderr=True))
        with bar:
            task = bar.add_task("x", total=10)
            for k in range(10):
                bar.advance(task)
                if k == 5:
                    logging.getLogger("drivegain.test").warning("a message in the middle")
                time.sleep(0.01)
    lines = _screen_lines(tty.getvalue())
    (hit,) = [ln for ln in lines if "a message in the middle" in ln]
    assert "━" not in hit and "working" not in hit  # not glued onto the bar


def test_piped_output_is_not_wrapped() -> None:
    pipe = io.StringIO()
    c = con.make_console(pipe)
    assert not c.is_terminal
    text = " ".join(f"word{k}" for k in range(60))  # about 400 columns
    c.print(text)
    assert pipe.getvalue() == text + "\n"


def test_piped_logging_is_plain_lines(monkeypatch) -> None:
    pipe = io.StringIO()
    monkeypatch.setattr(sys, "stderr", pipe)
    with _bare_root():
        handler = con.install_logging()
        assert type(handler) is logging.StreamHandler
        logging.getLogger("drivegain.test").info("x" * 300)
    (line,) = pipe.getvalue().splitlines()
    assert line.endswith("INFO drivegain.test: " + "x" * 300)


def test_an_existing_handler_is_kept() -> None:
    with _bare_root() as root:
        mine = logging.NullHandler()
        root.addHandler(mine)
        assert con.install_logging() is None and root.handlers == [mine]
