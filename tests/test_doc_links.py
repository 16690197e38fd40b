"""Every relative link in README.md, docs/ and bench/ names a file that exists and, with a
``#fragment``, a heading of that file (GitHub's anchors: lower case, punctuation dropped,
spaces to hyphens, ``-1``, ``-2`` for repeats).  A heading renamed once left README's link to
model.md's EXR section pointing nowhere."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
LINK = re.compile(r"\]\(([^)\s]+)\)")


def anchors(path: Path) -> set[str]:
    """The heading anchors of a markdown file (headings inside code fences are not)."""
    found: set[str] = set()
    repeats: dict[str, int] = {}
    fenced = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            fenced = not fenced
        heading = None if fenced else re.match(r"^#{1,6} (.*)", line)
        if heading:
            slug = re.sub(r"[^\w\- ]", "", heading.group(1).strip().lower()).replace(" ", "-")
            n = repeats.get(slug, 0)
            repeats[slug] = n + 1
            found.add(slug if n == 0 else f"{slug}-{n}")
    return found


def markdown_files() -> list[Path]:
    return [ROOT / "README.md", *sorted(ROOT.glob("docs/**/*.md")),
            *sorted(ROOT.glob("bench/*.md"))]


def test_the_anchors_follow_github():
    assert {"renderer-vector-passes-and-exr-clblurvectors-clblurioexr", "conventions"} <= \
        anchors(ROOT / "docs" / "model.md") | anchors(ROOT / "README.md")


@pytest.mark.parametrize("doc", markdown_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(doc):
    broken = []
    for target in LINK.findall(doc.read_text(encoding="utf-8")):
        if re.match(r"^[a-z]+:", target):  # http:, https:, mailto:
            continue
        path, _, fragment = target.partition("#")
        dest = (doc.parent / path).resolve() if path else doc
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif fragment and dest.suffix == ".md" and fragment not in anchors(dest):
            broken.append(f"{target}: no heading #{fragment}")
    assert not broken, broken
