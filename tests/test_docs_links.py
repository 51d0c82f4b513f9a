"""Every relative link in README.md, CONTRIBUTING.md and docs/ names a file or folder that exists.

A link `[text](target)` or image `![alt](target)` outside code blocks and code spans is checked; its `#anchor` is
ignored, so `page.md#section` fails exactly when `page.md` is missing. Links with a scheme (https:, mailto:) and
anchor-only links are left alone.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", ROOT / "CONTRIBUTING.md", *(ROOT / "docs").rglob("*.md")])
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
SCHEME = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")


def relative_links(text: str) -> list[str]:
    """The relative link targets of a markdown text, outside fenced code blocks and inline code spans."""
    targets = []
    fenced = False
    for line in text.splitlines():
        if line.lstrip().startswith(("```", "~~~")):
            fenced = not fenced
            continue
        if fenced:
            continue
        prose = re.sub(r"`[^`]*`", "", line)
        for target in LINK.findall(prose):
            if not SCHEME.match(target) and not target.startswith("#"):
                targets.append(target)
    return targets


def test_link_finder_sees_links_and_skips_code():
    text = "see [a](docs/a.md#x) and ![p](img.png)\n`[no](code.md)`\n```\n[no](fenced.md)\n```\n[w](https://x.y)"
    assert relative_links(text) == ["docs/a.md#x", "img.png"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page: Path):
    broken = [target for target in relative_links(page.read_text(encoding="utf-8"))
              if not (page.parent / target.split("#", 1)[0]).exists()]
    assert not broken, f"{page.relative_to(ROOT)}: links to missing files: {broken}"
