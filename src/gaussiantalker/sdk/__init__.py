"""Shared pieces of the GaussianTalker SDK: bundle format, camera model, numerics constants, I/O, errors.

Imports neither the runtime nor the exporter (and never torch).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("gaussiantalker-sdk")  # the one version source: pyproject.toml, via the installed metadata
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"
