"""The documentation's links: every relative link in README.md and under docs/ names a file that
exists and, for a Markdown file, a heading it has (GitHub's anchor rule); every docs/ path that the
code's comments and help texts point users to exists."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)\s]+)\)")


def anchors(md: Path) -> set[str]:
    """GitHub's anchors of a Markdown file's headings: lower case, punctuation dropped, spaces to hyphens."""
    out = set()
    for line in md.read_text().splitlines():
        m = re.match(r"^#{1,6} (.*)", line)
        if m:
            out.add(re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-"))
    return out


def broken_links(md: Path) -> list[str]:
    bad = []
    for link in LINK.findall(md.read_text()):
        if re.match(r"^[a-z]+:", link):  # http:, https:, mailto:
            continue
        path, _, frag = link.partition("#")
        target = (md.parent / path) if path else md
        if not target.exists():
            bad.append(f"{md.name}: {link} (no such file)")
        elif frag and target.suffix == ".md" and frag not in anchors(target):
            bad.append(f"{md.name}: {link} (no such heading)")
    return bad


def test_a_broken_link_is_found(tmp_path):
    (tmp_path / "a.md").write_text("# Title here\n\n## Some section\n")
    doc = tmp_path / "doc.md"
    doc.write_text("[ok](a.md#some-section) [ok](a.md#title-here) [ok](#x) [web](https://e.org/y)\n\n# X\n")
    assert broken_links(doc) == []
    doc.write_text("[gone](b.md) [bad anchor](a.md#other)\n")
    assert broken_links(doc) == ["doc.md: b.md (no such file)", "doc.md: a.md#other (no such heading)"]


def test_readme_and_docs_links_resolve():
    docs = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    assert len(docs) >= 4
    bad = [b for md in docs for b in broken_links(md)]
    assert not bad, bad


def test_docs_the_code_points_to_exist():
    named = set()
    for py in [*(REPO / "favormap").rglob("*.py"), *(REPO / "tools").rglob("*.py")]:
        named.update(re.findall(r"docs/[\w./-]+\.md", py.read_text()))
    assert named, "the code names no docs"
    missing = sorted(p for p in named if not (REPO / p).exists())
    assert not missing, missing
