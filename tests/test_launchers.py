"""`gt-bench` and `gt-web` run the checkout's tools/: from this checkout they find it and put it first on sys.path;
from a copy of the package laid out as a wheel installs it (no tools/ beside it) they exit 2 with one line."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from gaussiantalker.cli import checkout

CHECKOUT = Path(__file__).resolve().parents[1]


def test_the_launchers_find_this_checkout():
    assert checkout.checkout_root() == CHECKOUT


@pytest.mark.parametrize("tool", ["bench", "browser"])
def test_entering_the_checkout_puts_it_first(monkeypatch, tool):
    monkeypatch.setattr(sys, "path", ["/elsewhere"])
    checkout.enter_checkout("gt-x", tool)
    assert sys.path[0] == str(CHECKOUT)


WHEEL_LAUNCH = """
import sys
sys.argv = ["{command}", "--help"]
from gaussiantalker.cli.{module} import main
main()
"""


@pytest.mark.parametrize("command, module", [
    ("gt-web", "web"),
    pytest.param("gt-bench", "bench", marks=pytest.mark.slow),  # its export-extra check imports torch (~2 s)
])
def test_outside_a_checkout_they_say_how_to_get_one(tmp_path, command, module):
    """The package copied into a site-packages-like folder: one line on stderr, exit 2, no traceback. (`gt-bench`
    checks the export extra first; here it is installed, so the checkout is what is missing.)"""
    site = tmp_path / "lib" / "python3" / "site-packages"
    shutil.copytree(CHECKOUT / "src" / "gaussiantalker", site / "gaussiantalker",
                    ignore=shutil.ignore_patterns("__pycache__"))
    code = WHEEL_LAUNCH.format(command=command, module=module)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                            env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"})
    assert result.returncode == 2, result.stderr
    assert result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{command}: runs from a source checkout of gaussiantalker-sdk")
    assert "pip install -e ." in lines[0]


def test_the_wheel_holds_no_benchmark_or_browser_harness(tmp_path):
    """`pip wheel .` packs src/gaussiantalker/ only: the launchers, never tools/ (benchmarks, the Chromium driver, the
    web harness) nor web/; gt-serve's own two pages are the only HTML it carries."""
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w",
                    str(tmp_path), str(CHECKOUT)], check=True, capture_output=True, timeout=300)
    import zipfile

    (wheel,) = tmp_path.glob("*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    code = [name for name in names if not name.endswith(".dist-info/RECORD") and ".dist-info/" not in name]
    assert "gaussiantalker/runtime/head.py" in code and "gaussiantalker/cli/bench.py" in code
    pages = {"gaussiantalker/serve/pages/client.html", "gaussiantalker/serve/pages/pixel.html"}
    assert pages <= set(code)  # an installed gt-serve serves them
    code = [name for name in code if name not in pages]
    tooling = [name for name in code if any(part in name for part in (
        "tools/", "/bench/", "/browser/", "chromium", "harness", "web_cli", "web_assets", "frame_digests", ".js",
        ".html"))]
    assert not tooling, tooling
    assert all(name.startswith("gaussiantalker/") for name in code), [n for n in code if
                                                                       not n.startswith("gaussiantalker/")]
