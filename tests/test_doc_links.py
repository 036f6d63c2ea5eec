"""Every relative link in the README, docs/ and experiments/README.md reaches a file, and every #anchor a heading.

A renamed section or a moved results file otherwise breaks the docs silently. Anchors follow GitHub's rule:
the heading lowercased, punctuation but hyphens and underscores dropped, spaces turned into hyphens, and a
repeated heading numbered -1, -2, ...
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", ROOT / "experiments" / "README.md", *(ROOT / "docs").glob("*.md")])
LINK = re.compile(r"\]\(([^)\s]+)\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)


def slug(heading: str) -> str:
    text = re.sub(r"[`*_]{1,2}(?=\S)|(?<=\S)[`*_]{1,2}", "", heading.strip()).lower()
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)  # a link in a heading keeps its text
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for line in FENCE.sub("", page.read_text()).splitlines():
        if m := re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line):
            base = slug(m.group(1))
            n = seen.get(base, 0)
            seen[base] = n + 1
            out.add(base if n == 0 else f"{base}-{n}")
    return out


def test_slug_follows_githubs_rule():
    assert slug("Peg at 1 M steps") == "peg-at-1-m-steps"
    assert slug("Why the first agent grasps thin") == "why-the-first-agent-grasps-thin"
    assert slug("`--eta auto`: the rules") == "--eta-auto-the-rules"
    assert slug("C physics") == "c-physics"


def broken_links(page: Path) -> list[str]:
    broken = []
    for target in LINK.findall(FENCE.sub("", page.read_text())):
        if re.match(r"[a-z]+:", target):  # http(s), mailto: not checked offline
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading with that anchor")
    return broken


def test_a_missing_file_a_missing_anchor_and_a_repeated_heading_are_told_apart(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# Top\n## Part\n## Part\n```\n# not a heading\n[x](gone.md)\n```\n"
                    "[a](#part-1) [b](#part-2) [c](gone.md) [d](page.md#top) [e](#not-a-heading) [f](https://x.org/#y)\n")
    assert broken_links(page) == ["#part-2: no heading with that anchor", "gone.md: no such file",
                                  "#not-a-heading: no heading with that anchor"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_and_anchor_resolves(page: Path):
    broken = broken_links(page)
    assert not broken, f"{page.relative_to(ROOT)}: " + "; ".join(broken)
