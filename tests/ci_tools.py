"""Tests that need a tool CI installs (CONTRIBUTING.md, "CI"): they skip where it is missing, and fail instead
where the environment variable CI is set (non-empty), so a failed install cannot turn CI's tests into skips."""

from __future__ import annotations

import importlib.util
import os

import pytest

# What installs each tool in CI, named in the failure.
BROWSER_INSTALL = ".ci/browser (Debian's chromium, LAM's npm renderer and web/'s npm install)"


def need(missing: str | None, installed_by: str, *, module_level: bool = False) -> None:
    """Nothing when `missing` is None; else skip with it, or fail with it where CI is set. `missing` says what is
    absent and how to install it; `installed_by` names the CI step that installs it. `module_level`: called while
    a test module is imported (a failure there is a collection error, as a failed import would be)."""
    if missing is None:
        return
    if os.environ.get("CI"):
        pytest.fail(f"CI is set but {missing}; in CI {installed_by} installs it, so this test must run",
                    pytrace=False)
    pytest.skip(missing, allow_module_level=module_level)


def need_module(module: str, extra: str, *, module_level: bool = False) -> None:
    """`need` for an importable module of one of the project's extras (which .ci/install installs)."""
    missing = None
    if importlib.util.find_spec(module) is None:
        missing = f"{module} is not installed (the {extra} extra: pip install '.[{extra}]')"
    need(missing, ".ci/install", module_level=module_level)


def need_chromium() -> None:
    """`need` for Debian's chromium (the browser tests: tests/test_lam_web.py, tests/test_live_browser.py,
    tests/test_web_player.py)."""
    from tools.browser.chromium import ChromiumMissing, chromium_path

    try:
        chromium_path()
    except ChromiumMissing as exc:
        need(str(exc), BROWSER_INSTALL)


def need_lam_renderer() -> None:
    """`need` for chromium and LAM's npm web renderer in its cache (docs/lam-web.md)."""
    from tools.bench import lam_web

    need_chromium()
    need(lam_web.check_installed(), BROWSER_INSTALL)
