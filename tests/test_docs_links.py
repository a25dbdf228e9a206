"""Every link in the README and in docs/ leads somewhere: a file of the repository, and a heading of it
where the link names one (``page.md#a-heading``, GitHub's anchors)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", ROOT / "deploy" / "README.md", *(ROOT / "docs").glob("*.md")])

PENDING_PAGES = {"docs/raspberry-pi.md", "docs/doctor.md"}
"""Pages other changes of this round write (issue 31), linked from the README and docs/results.md already.
A link to one of them may go nowhere only while it does not exist; once it does, its anchors are checked
like any other page's. Remove them from here when they have landed."""

_LINK = re.compile(r"(?<!!)\[(?:[^\]\[]|\[[^\]]*\])*\]\(([^()\s]+)\)")
_FENCE = re.compile(r"^\s*(```|~~~)")


def _prose(text: str, code_spans: bool = False) -> str:
    """``text`` without its fenced code blocks and (unless ``code_spans``) its inline code spans, where
    brackets are code, not links."""
    out, fenced = [], False
    for line in text.splitlines():
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            out.append(line if code_spans else re.sub(r"`[^`]*`", "", line))
    return "\n".join(out)


def links(text: str) -> list[str]:
    """The targets of the Markdown links of ``text`` (images left out)."""
    return _LINK.findall(_prose(text))


def anchors(text: str) -> set[str]:
    """GitHub's anchors of the headings of ``text``: lower case, punctuation dropped, spaces as hyphens, a
    repeated heading numbered (``-1``, ``-2``)."""
    seen: dict[str, int] = {}
    out = set()
    for line in _prose(text, code_spans=True).splitlines():
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        slug = re.sub(r"[^\w\- ]", "", m.group(1).lower()).replace(" ", "-")
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def broken_links(page: Path) -> list[str]:
    text = page.read_text(encoding="utf-8")
    bad = []
    for target in links(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto:: not followed
            continue
        path, _, fragment = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        rel = dest.relative_to(ROOT).as_posix() if dest.is_relative_to(ROOT) else dest.name
        if not dest.exists():
            if rel not in PENDING_PAGES:
                bad.append(f"{target}: no such file")
            continue
        if fragment and dest.suffix == ".md" and fragment not in anchors(dest.read_text(encoding="utf-8")):
            bad.append(f"{target}: no heading #{fragment} in {rel}")
    return bad


def test_the_link_reader_finds_links_anchors_and_what_is_missing(tmp_path: Path) -> None:
    text = (
        "# A title\n## What `ipt` does, each step\n## The sender: 60 Hz at 1920×2160, from the first frame\n"
        "## Notes\n## Notes\n"
        "See [a](other.md#b-c), ![img](pic.png), [x [y] z](#notes-1) and `[code](not-a-link.md)`.\n"
        "```\n[in a fence](fenced.md)\n```\n[web](https://example.org/a_(b)) [mail](mailto:a@b.c)\n"
    )
    assert links(text) == ["other.md#b-c", "#notes-1", "mailto:a@b.c"]
    assert anchors(text) == {
        "a-title",
        "what-ipt-does-each-step",
        "the-sender-60-hz-at-19202160-from-the-first-frame",
        "notes",
        "notes-1",
    }
    page = tmp_path / "page.md"
    page.write_text(text, encoding="utf-8")
    (tmp_path / "other.md").write_text("# B c\n", encoding="utf-8")
    assert broken_links(page) == []
    page.write_text(text.replace("#b-c", "#d").replace("#notes-1", "#notes-2"), encoding="utf-8")
    assert broken_links(page) == ["other.md#d: no heading #d in other.md", "#notes-2: no heading #notes-2 in page.md"]


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(ROOT).as_posix() for p in PAGES])
def test_every_link_resolves(page: Path) -> None:
    assert broken_links(page) == []


def test_the_readme_is_a_front_door() -> None:
    """At most 250 lines; it says where to start reading and where the figures are."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250
    assert "docs/architecture.md" in links(text)
    assert "docs/results.md" in links(text)
