"""Import rules: the runtime and sdk never import torch (checked in a fresh interpreter); sdk imports neither side."""

from __future__ import annotations

import subprocess
import sys

import pytest

CHECK = """
import sys
import {module}
bad = sorted(m for m in sys.modules if m == "torch" or m.startswith("torch.") or m in {forbidden})
print(",".join(bad))
"""


@pytest.mark.parametrize("module, forbidden", [
    ("gaussiantalker.runtime", ()),
    ("gaussiantalker.runtime.head", ()),
    ("gaussiantalker.runtime.splatter", ()),
    ("gaussiantalker.sdk.bundle", ("gaussiantalker.runtime", "gaussiantalker.exporter")),
    ("gaussiantalker.sdk.audio", ("gaussiantalker.runtime", "gaussiantalker.exporter")),
    ("gaussiantalker.sdk.video", ("gaussiantalker.runtime", "gaussiantalker.exporter")),
    ("gaussiantalker.sdk.drive", ("gaussiantalker.runtime", "gaussiantalker.exporter")),
])
def test_module_does_not_pull_forbidden_imports(module, forbidden):
    code = CHECK.format(module=module, forbidden=repr(set(forbidden)) if forbidden else "()")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "", f"{module} imported {result.stdout.strip()}"


def test_the_check_itself_detects_torch():
    """Guard against a check that cannot fail: importing the exporter does pull torch."""
    code = CHECK.format(module="gaussiantalker.exporter.speaker", forbidden="()")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "torch" in result.stdout
