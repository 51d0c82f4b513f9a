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
    ("gaussiantalker.runtime.splat.gl", ()),
    ("gaussiantalker.runtime.live", ()),
    ("gaussiantalker.cli.entry", ()),  # the console scripts check for the export extra before any torch
    ("gaussiantalker.cli.bench", ()),
    ("gaussiantalker.cli.web", ()),
    ("gaussiantalker.cli.serve", ()),
    ("gaussiantalker.cli.render", ()),
    ("gaussiantalker.batch", ("gaussiantalker.exporter", "gaussiantalker.serve")),  # workers load the runtime alone
    ("gaussiantalker.batch.worker", ("gaussiantalker.exporter",)),
    ("gaussiantalker.serve.wire", ("gaussiantalker.exporter", "aiohttp", "jwt")),  # a bare runtime reads it
    ("gaussiantalker.sdk.bundle", ("gaussiantalker.runtime", "gaussiantalker.exporter")),
    ("gaussiantalker.sdk.audio", ("gaussiantalker.runtime", "gaussiantalker.exporter")),
    ("gaussiantalker.sdk.video", ("gaussiantalker.runtime", "gaussiantalker.exporter")),
    ("gaussiantalker.sdk.drive", ("gaussiantalker.runtime", "gaussiantalker.exporter")),
])
def test_module_does_not_pull_forbidden_imports(module, forbidden):
    code = CHECK.format(module=module, forbidden=repr(set(forbidden)) if forbidden else "()")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "", f"{module} imported {result.stdout.strip()}"


def test_the_check_itself_detects_a_forbidden_import():
    """Guard against a check that cannot fail, without importing torch (~1.5 s): the sdk's bundle reader does
    import numpy, so a check forbidding numpy reports it."""
    code = CHECK.format(module="gaussiantalker.sdk.bundle", forbidden=repr({"numpy"}))
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "numpy"


@pytest.mark.slow  # imports torch in a fresh interpreter (~1.5 s); the quick guard is the numpy one above
def test_the_check_itself_detects_torch():
    """Guard against a check that cannot fail: importing the exporter does pull torch (where torch is installed;
    .ci/runtime-only also runs this file in a virtualenv without it)."""
    pytest.importorskip("torch")
    code = CHECK.format(module="gaussiantalker.exporter.model.speaker", forbidden="()")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "torch" in result.stdout


BLOCKED_EXPORT_EXTRA = """
import sys
sys.modules["torch"] = None  # `import torch` now raises ImportError, as in a runtime-only install
from {module} import {entry}
sys.argv = ["{command}", "speaker.ckpt"]
{entry}()
"""


@pytest.mark.parametrize("command, module, entry", [
    ("gt-export", "gaussiantalker.cli.entry", "gt_export"),
    pytest.param("gt-bench", "gaussiantalker.cli.bench", "main", marks=pytest.mark.slow),  # the same check
])
def test_exporter_commands_without_torch_say_what_to_install(command, module, entry):
    """Without the export extra, gt-export / gt-bench exit 2 with one line naming the extra (no traceback); gt-bench
    says so before looking for the checkout its benchmarks run from (a runtime-only install has neither)."""
    code = BLOCKED_EXPORT_EXTRA.format(module=module, entry=entry, command=command)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 2, result.stderr
    assert result.stdout == ""
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{command}: needs the 'export' extra (")
    missing = lines[0].split("(", 1)[1].split(" not installed)", 1)[0].split(", ")
    assert "torch" in missing  # with the extra installed (the main CI job) only the blocked torch is missing
    assert 'gaussiantalker-sdk[export]' in lines[0]


def test_runtime_reexports_what_an_app_needs():
    """`gaussiantalker.runtime` alone gives an app the head, the drive types, the camera and every error type."""
    import gaussiantalker.runtime as runtime
    from gaussiantalker.sdk import errors

    for name in ("TalkingHead", "Camera", "HeadPose", "FrameDrive", "BlendshapeDrive", "MotionTrack", "load_motion",
                 "ARKIT_BLENDSHAPES", "__version__"):
        assert hasattr(runtime, name), name
    error_types = {n for n, v in vars(errors).items() if isinstance(v, type) and issubclass(v, Exception)}
    # Checkpoints and avatar files to import are the exporter's input, not the runtime's.
    assert error_types - {"CheckpointError", "ImportFormatError"} <= set(runtime.__all__)
    assert runtime.__version__ == __import__("importlib.metadata").metadata.version("gaussiantalker-sdk")
