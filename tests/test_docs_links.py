"""Every relative link of README.md, DEVELOPERS.md and docs/ leads somewhere: the file exists and the ``#anchor``
names one of its headings as GitHub renders it (lower case, punctuation dropped, spaces to hyphens, ``-1``,
``-2`` ... for repeated headings), and every table ends before the text after it. Web addresses are not followed
(no network here)."""

from __future__ import annotations

import re
from collections import Counter
from functools import cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCUMENTS = [REPO / "README.md", REPO / "DEVELOPERS.md", *sorted((REPO / "docs").glob("*.md"))]
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)")
IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s]+)\)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
FENCE = re.compile(r"^\s*(```|~~~)")
TABLE_DELIMITER = re.compile(r"^\s*\|?\s*:?-{3,}:?\s*(\|\s*:?-{3,}:?\s*)*\|?\s*$")  # the row under a header


def prose_lines(path: Path) -> list[tuple[int, str]]:
    """``(line number, line)`` of ``path`` outside fenced code blocks (a link there is code, not a link)."""
    lines, fenced = [], False
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if FENCE.match(line):
            fenced = not fenced
        elif not fenced:
            lines.append((number, line))
    return lines


def heading_slug(text: str) -> str:
    """The anchor GitHub gives a heading: markup and punctuation dropped, lower case, each space a hyphen."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)  # a link in a heading: its text
    text = text.replace("`", "").strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


@cache
def anchors(path: Path) -> frozenset[str]:
    """Every heading anchor of ``path``, repeated headings numbered as GitHub numbers them."""
    seen: Counter[str] = Counter()
    found = set()
    for _, line in prose_lines(path):
        match = HEADING.match(line)
        if match:
            slug = heading_slug(match.group(2))
            found.add(slug if seen[slug] == 0 else f"{slug}-{seen[slug]}")
            seen[slug] += 1
    return frozenset(found)


def relative_links(path: Path) -> list[tuple[int, str]]:
    """``(line number, target)`` of each link and image in ``path`` that is not a web or mail address."""
    links = []
    for number, line in prose_lines(path):
        line = re.sub(r"`[^`]*`", "", line)  # inline code holds no links
        for pattern in (LINK, IMAGE):
            for target in pattern.findall(line):
                if not re.match(r"^[a-z][a-z0-9+.-]*:", target):
                    links.append((number, target))
    return links


def test_the_heading_slugs_are_githubs():
    assert heading_slug("Transfer: does it teach scenes never seen?") == "transfer-does-it-teach-scenes-never-seen"
    assert heading_slug("The ground recoloured (`ground_recolour_p`)") == "the-ground-recoloured-ground_recolour_p"
    assert heading_slug("Another renderer (`bench_foreign`)") == "another-renderer-bench_foreign"
    assert heading_slug("Depth, 0–1000 m & sky") == "depth-01000-m--sky"


def test_the_documents_have_links_to_check():
    assert sum(len(relative_links(document)) for document in DOCUMENTS) >= 50


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda path: str(path.relative_to(REPO)))
def test_every_relative_link_leads_to_a_file_and_heading_that_exist(document):
    broken = []
    for number, target in relative_links(document):
        file_part, _, anchor = target.partition("#")
        linked = (document.parent / file_part).resolve() if file_part else document
        if not linked.exists():
            shown = linked.relative_to(REPO) if linked.is_relative_to(REPO) else linked
            broken.append(f"line {number}: {target}: no file {shown}")
        elif anchor and linked.suffix == ".md" and anchor not in anchors(linked):
            broken.append(f"line {number}: {target}: no heading #{anchor} in {linked.relative_to(REPO)}")
    assert not broken, f"{document.relative_to(REPO)}:\n" + "\n".join(broken)


def test_every_document_the_code_points_users_to_exists():
    """Messages, docstrings and config comments name ``docs/NAME.md``: each is there."""
    named = set()
    for folder in ("dapm_lightning", "benchmarks", "scripts", "configs"):
        for path in (REPO / folder).rglob("*"):
            if path.suffix in {".py", ".yaml", ".sh"}:
                named.update(re.findall(r"\bdocs/[\w-]+\.md", path.read_text(encoding="utf-8")))
    assert len(named) >= 5, named
    assert not sorted(name for name in named if not (REPO / name).exists())


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda path: str(path.relative_to(REPO)))
def test_every_table_ends_at_a_blank_line(document):
    """A text line right after a table's last row renders as one more row of it (GitHub's Markdown)."""
    glued, in_table, previous = [], False, ""
    for number, line in prose_lines(document):
        if TABLE_DELIMITER.match(line) and previous.lstrip().startswith("|"):
            in_table = True  # a header row and its delimiter row: a table starts
        elif in_table and not line.lstrip().startswith("|"):
            if line.strip():
                glued.append(number)
            in_table = False
        previous = line
    assert not glued, f"{document.relative_to(REPO)}: a table runs into the text after it at line(s) {glued}"
