"""The `export` extra's check: a runtime-only install (`pip install gaussiantalker-sdk`, no torch) running an
exporter command gets one line saying what to install instead of a traceback."""

from __future__ import annotations

import sys

# What the exporter side imports beyond the runtime's dependencies (the `export` extra of pyproject.toml).
EXPORT_EXTRA_MODULES = ("torch", "onnx", "onnxscript", "plyfile")
INSTALL_HINT = ('pip install torch==2.13.0 && pip install "gaussiantalker-sdk[export]" '
                "(torch first, so pip keeps the CPU build)")


def missing_export_modules() -> list[str]:
    """The export extra's modules that cannot be imported here."""
    missing = []
    for name in EXPORT_EXTRA_MODULES:
        try:
            __import__(name)
        except ImportError:
            missing.append(name)
    return missing


def require_export_extra(command: str) -> None:
    """Exit with status 2 and one line on stderr when the export extra is not installed."""
    missing = missing_export_modules()
    if missing:
        sys.stderr.write(f"{command}: needs the 'export' extra ({', '.join(missing)} not installed): "
                         f"{INSTALL_HINT}\n")
        raise SystemExit(2)
