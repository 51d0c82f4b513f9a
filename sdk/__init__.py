"""Shared pieces of the GaussianTalker SDK: bundle format, camera model, numerics constants, I/O, errors.

Imports neither the runtime nor the exporter (and never torch).
"""

__version__ = "0.1.0"
