"""drivegain: global identification of robot drive gains and dynamics."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("drivegain")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"

__all__ = ["__version__"]
