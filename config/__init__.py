"""Configuration files of drivegain and their loaders.

The TOML files shipped here (robot descriptions, payloads, simulation truth, drive EDS, bus and
acquisition defaults) are package data: :func:`resource_path` finds them in an installed package.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from drivegain.config.payload import Payload, load_payload
from drivegain.config.robot import Coupling, Joint, Robot, load_robot
from drivegain.config.truth import Truth, load_truth

__all__ = [
    "Coupling",
    "Joint",
    "Payload",
    "Robot",
    "Truth",
    "load_payload",
    "load_robot",
    "load_truth",
    "resource_path",
]


def resource_path(name: str) -> Path:
    """Path of a file shipped in ``drivegain.config``, e.g. ``"payloads/x.toml"``.

    Raises
    ------
    FileNotFoundError
        If no such file is shipped.
    """
    path = Path(str(resources.files("drivegain.config").joinpath(name)))
    if not path.is_file():
        raise FileNotFoundError(f"no shipped config file {name!r}")
    return path
