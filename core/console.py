"""The terminal: one rich console per stream, shared by progress displays and log lines.

On a terminal, log records go through rich's logging handler on the same console as the
progress bars, so a record printed while a bar is live appears above the bar instead of being
glued onto it. When the output is piped or redirected there is no live display; records are
plain lines, and rich output is not wrapped at a guessed width of 80 columns (a pipe has no
width: a long line stays one line for ``grep`` and log files).
"""

from __future__ import annotations

import logging
import sys
from typing import TYPE_CHECKING, TextIO

if TYPE_CHECKING:
    from rich.console import Console

#: Width given to rich when the stream is not a terminal: wide enough never to wrap a line.
PIPE_WIDTH = 100_000
PLAIN_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"

_consoles: dict[tuple[int, int], Console] = {}


def make_console(file: TextIO | None = None, *, stderr: bool = False) -> Console:
    """A rich console on ``file`` (default stdout, or stderr) that does not wrap when piped."""
    from rich.console import Console

    probe = Console(file=file, stderr=stderr)
    if probe.is_terminal:
        return probe
    return Console(file=file, stderr=stderr, width=PIPE_WIDTH, soft_wrap=True)


def console(*, stderr: bool = True) -> Console:
    """The shared console of stderr (default) or stdout.

    One object per stream and per underlying file (tests and ``contextlib.redirect_*`` swap
    ``sys.stderr``; a new file gets a new console), so every progress display and the log
    handler of that stream are the same object.
    """
    stream = sys.stderr if stderr else sys.stdout
    key = (int(stderr), id(stream))
    found = _consoles.get(key)
    if found is None:
        if len(_consoles) > 8:  # streams come and go in tests: keep only recent ones
            _consoles.clear()
        found = make_console(stderr=stderr)
        _consoles[key] = found
    return found


def install_logging(debug: bool = False) -> logging.Handler | None:
    """Route the root logger to stderr: through rich on a terminal, plain lines otherwise.

    Like :func:`logging.basicConfig`, nothing changes when the root logger already has a
    handler (a daemon's JSON lines, a test's capture).

    Parameters
    ----------
    debug
        DEBUG level instead of INFO.

    Returns
    -------
    logging.Handler or None
        The handler installed, or None when one was already there.
    """
    root = logging.getLogger()
    if root.handlers:
        return None
    con = console(stderr=True)
    handler: logging.Handler
    if con.is_terminal:
        from rich.logging import RichHandler

        handler = RichHandler(console=con, show_path=False, log_time_format="%H:%M:%S")
        handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
    else:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter(PLAIN_FORMAT))
    root.addHandler(handler)
    root.setLevel(logging.DEBUG if debug else logging.INFO)
    return handler
