"""The README's and ARCHITECTURE.md's relative links lead somewhere: every linked file exists, and every `#anchor`
into a Markdown file (BENCHMARKS.md's sections, format_spec's) is one of that file's headings as GitHub names them
(docs61: the README links its figures to BENCHMARKS.md's sections instead of quoting them)."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
from conftest import ROOT

DOCS = ["README.md", "ARCHITECTURE.md", "docs/other_clients.md"]
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(([^()\s]+)\)")


def github_anchor(heading: str) -> str:
    """GitHub's id for a heading: lower case, punctuation dropped (word characters, spaces and hyphens kept),
    each space a hyphen."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(markdown: str) -> set[str]:
    """Every heading's id, outside fenced code; a repeated id gets -1, -2, ... as on GitHub."""
    seen: dict[str, int] = {}
    found, fenced = set(), False
    for line in markdown.splitlines():
        if line.startswith("```"):
            fenced = not fenced
            continue
        heading = None if fenced else re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if heading:
            base = github_anchor(heading.group(1))
            count = seen.get(base, 0)
            seen[base] = count + 1
            found.add(base if count == 0 else f"{base}-{count}")
    return found


def links(markdown: str) -> list[str]:
    """The link targets outside fenced code and inline code."""
    out, fenced = [], False
    for line in markdown.splitlines():
        if line.startswith("```"):
            fenced = not fenced
            continue
        if not fenced:
            out += LINK.findall(re.sub(r"`[^`]*`", "", line))
    return out


def test_github_anchor_names_headings_as_github_does():
    assert github_anchor("Decode speed (`bench/bench_decode.py`)") == "decode-speed-benchbench_decodepy"
    assert github_anchor("The 2 + 8 px rule") == "the-2--8-px-rule"
    assert anchors("# A\n```\n# not a heading\n```\n## A\n") == {"a", "a-1"}


@pytest.mark.parametrize("doc", DOCS)
def test_relative_links_and_anchors_resolve(doc):
    source = ROOT / doc
    text = source.read_text()
    targets = [t for t in links(text) if not re.match(r"^[a-z]+:", t)]
    assert targets, f"{doc}: no relative link found: the link pattern is wrong"
    broken = []
    for target in targets:
        path, _, anchor = target.partition("#")
        linked = (source.parent / path).resolve() if path else source
        if not linked.exists():
            broken.append(f"{target}: no such file")
        elif anchor and linked.suffix == ".md" and anchor not in anchors(Path(linked).read_text()):
            broken.append(f"{target}: no heading {anchor!r} in {linked.name}")
    assert not broken, f"{doc}:\n" + "\n".join(broken)
