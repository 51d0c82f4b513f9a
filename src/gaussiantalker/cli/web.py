"""`gt-web`'s launcher: the browser player's command line (tools/browser/web_cli.py, docs/web.md), run from the
source checkout this package is installed from."""

from __future__ import annotations

from .checkout import enter_checkout


def main() -> None:
    """`gt-web`: render frames with the browser player in headless Chromium, or install its npm packages."""
    enter_checkout("gt-web", "browser")
    from tools.browser.web_cli import main as web_main

    web_main()
