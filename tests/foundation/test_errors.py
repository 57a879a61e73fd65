"""The exception tree: one line naming the file and key, kept across a process boundary."""

from __future__ import annotations

import pickle

import pytest

from drivegain.errors import ConfigError, DataError, DrivegainError, InputError


@pytest.mark.parametrize(
    ("error", "line"),
    [
        (DataError("bad message", file="/x/run.mcap"), "/x/run.mcap: bad message"),
        (ConfigError("not a number", file="r.toml", key="a.b"), "r.toml: key 'a.b': not a number"),
        (InputError("no such option"), "no such option"),
    ],
)
def test_an_input_error_survives_pickling_whole(error: InputError, line: str) -> None:
    assert str(error) == line
    back = pickle.loads(pickle.dumps(error))  # what a worker process sends back
    assert type(back) is type(error) and isinstance(back, DrivegainError)
    assert str(back) == line
    assert (back.message, back.file, back.key) == (error.message, error.file, error.key)
