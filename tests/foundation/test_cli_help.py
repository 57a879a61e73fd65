"""``--help`` of every subcommand: defaults shown, a description, examples that parse and name
files that are shipped."""

from __future__ import annotations

import argparse
import re
import shlex
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivegain.cli import build_parser
from drivegain.config import resource_path

REPO = Path(__file__).resolve().parents[2]


def _parsers(
    parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, (*path, name))


ALL = list(_parsers(build_parser()))
SUBCOMMANDS = [(p, sub) for p, sub in ALL if p]


def _ids(items: list[tuple[tuple[str, ...], argparse.ArgumentParser]]) -> list[str]:
    return [" ".join(p) or "drivegain" for p, _ in items]


@pytest.mark.parametrize(("path", "parser"), ALL, ids=_ids(ALL))
def test_every_option_with_a_default_shows_it(path, parser) -> None:
    text = " ".join(parser.format_help().split())  # argparse wraps lines: compare unwrapped
    for action in parser._actions:
        default = action.default
        if isinstance(action, argparse._HelpAction | argparse._VersionAction):
            continue
        if default in (None, False, argparse.SUPPRESS) or not action.option_strings:
            continue
        assert action.help, action.option_strings
        shown = f"default: {default}" in text or f"default {default}" in text
        assert shown, f"{action.option_strings} of '{' '.join(path)}' hides {default!r}"


@pytest.mark.parametrize(("path", "parser"), SUBCOMMANDS, ids=_ids(SUBCOMMANDS))
def test_every_subcommand_has_a_description_and_examples(path, parser) -> None:
    text = parser.format_help()
    assert parser.description, path
    examples = _examples(parser)
    assert examples, f"'{' '.join(path)}' --help shows no example"
    for line in examples:
        words = shlex.split(line.split("   #")[0])
        assert words[0] == "drivegain"
        assert " ".join(path) in line
        if "--help" in words:
            continue
        build_parser().parse_args(words[1:])  # parses as written (SystemExit otherwise)
        for word in words:
            if word.startswith("config/"):
                # a shipped file: in the source tree and in the installed package
                assert (REPO / word).is_file(), word
                assert resource_path(word.removeprefix("config/")).is_file(), word
    assert "example" in text


def _examples(parser: argparse.ArgumentParser) -> list[str]:
    text = "\n".join(filter(None, [parser.description, parser.epilog]))
    return [m.strip() for m in re.findall(r"^\s+(drivegain .*)$", text, flags=re.M)]
