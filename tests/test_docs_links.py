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


BENCH = ROOT / "docs" / "bench"


def cited_in(pages_text: str, path: Path) -> bool:
    """Whether `path` (a file under docs/bench) is named by the pages: by its path (from the repository or from
    docs/), by a folder above it up to docs/bench, or as the companion of a file so named (the same name but the
    suffix: the JSON or plot a bench writes beside its page)."""
    def named(candidate: Path) -> bool:
        for ancestor in (candidate, *candidate.parents):
            if ancestor == BENCH:
                return False
            for spelling in (ancestor.relative_to(ROOT), ancestor.relative_to(ROOT / "docs")):
                if str(spelling) in pages_text:
                    return True
        return False

    return named(path) or any(named(other) for other in path.parent.glob(path.stem + ".*") if other != path)


def test_bench_citation_check_sees_paths_folders_and_companions(tmp_path):
    page = "see bench/live/live.md and docs/bench/zen5/ and bench/sweep-demo.md"
    assert cited_in(page, BENCH / "live" / "live.md")
    assert cited_in(page, BENCH / "zen5" / "vs-d674d5e" / "live-now.md")
    assert cited_in(page, BENCH / "sweep-demo.json")
    assert not cited_in(page, BENCH / "live-128" / "live.md")
    assert not cited_in("see bench/", BENCH / "live" / "live.md")


def test_every_bench_output_is_cited_by_a_page():
    """docs/bench holds what the pages cite and nothing else (docs/README.md indexes it): an output no page names
    is an archive nobody reads, so remove it or cite it."""
    pages_text = "\n".join(page.read_text(encoding="utf-8") for page in PAGES if BENCH not in page.parents)
    orphans = [str(path.relative_to(ROOT)) for path in sorted(BENCH.rglob("*"))
               if path.is_file() and not cited_in(pages_text, path)]
    assert not orphans, f"docs/bench files no page names (outside docs/bench): {orphans}"
