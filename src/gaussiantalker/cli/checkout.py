"""Where `gt-bench` and `gt-web` find what they run: the tools/ folder of the source checkout this package is
installed from (`pip install -e .`). A wheel carries no tools/, so there they stop with one line."""

from __future__ import annotations

import sys
from pathlib import Path

HOW_TO_CHECKOUT = "clone the SDK's repository and run `pip install -e .` in it, then run this command again"


def checkout_root() -> Path | None:
    """The checkout holding this package's source and tools/, or None where the package is installed from a
    wheel."""
    here = Path(__file__).resolve().parent
    root = here.parents[2]  # src/gaussiantalker/cli/ -> the checkout
    if here == root / "src" / "gaussiantalker" / "cli" and (root / "tools" / "__init__.py").is_file():
        return root
    return None


def enter_checkout(command: str, tool: str) -> None:
    """Put the checkout first on sys.path so `tools.<tool>` imports from it; outside a checkout, exit with status 2
    and one line on stderr."""
    root = checkout_root()
    if root is None or not (root / "tools" / tool / "__init__.py").is_file():
        sys.stderr.write(f"{command}: runs from a source checkout of gaussiantalker-sdk (its tools/{tool}/ is not "
                         f"part of the installed package): {HOW_TO_CHECKOUT}\n")
        raise SystemExit(2)
    sys.path.insert(0, str(root))
