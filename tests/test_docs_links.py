"""Every relative link and image in README.md and docs/ points at a file of the repository, every
#anchor at a heading of its page (as GitHub names them), and no code comment points at a README
section or at a file outside the repository: the documentation can be moved around without a
reader meeting a dead link."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^(```|~~~)")


def pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _prose(text: str, keep_code: bool = False) -> list[str]:
    """The lines outside fenced code blocks, inline code removed unless ``keep_code``."""
    out, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line.lstrip()):
            fenced = not fenced
            continue
        if not fenced:
            out.append(line if keep_code else re.sub(r"`[^`]*`", "", line))
    return out


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped (letters of any script, digits,
    '-' and '_' kept), spaces to '-'."""
    text = re.sub(r"`", "", heading.strip().lower())
    text = "".join(c for c in text if c.isalnum() or c in " -_")
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for line in _prose(page.read_text(), keep_code=True):
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        base = slug(m.group(1))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def broken_links(page: Path) -> list[str]:
    problems = []
    for line in _prose(page.read_text()):
        for target in LINK.findall(line):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            if not dest.is_relative_to(ROOT):
                problems.append(f"{target}: outside the repository")
            elif not dest.exists():
                problems.append(f"{target}: no such file")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                problems.append(f"{target}: no heading with that anchor in {dest.relative_to(ROOT)}")
    return problems


@pytest.mark.parametrize("page", pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    assert broken_links(page) == []


def test_the_checker_finds_a_dead_link_and_a_dead_anchor(tmp_path, monkeypatch):
    monkeypatch.setitem(globals(), "ROOT", tmp_path)
    (tmp_path / "a.md").write_text("# Title `x` — one\n\n## Two, three\n")
    page = tmp_path / "b.md"
    page.write_text("[ok](a.md#title-x--one) [ok](a.md#two-three) [ok](#here) ![no](img.png)\n"
                    "[no](a.md#four) [no](../out.md) `[code](ignored.md)`\n\n```\n[fenced](ignored.md)\n```\n"
                    "## Here\n")
    assert broken_links(page) == ["img.png: no such file", "a.md#four: no heading with that anchor in a.md",
                                  "../out.md: outside the repository"]


def test_the_readme_stays_a_front_page():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 250


SOURCES = ("smgs", "baselines", "protocols", "reports", "bench", "tools", "configs", "tests")


def test_no_code_comment_points_at_a_readme_section_or_outside_the_repository():
    bad = re.compile(r"README[\s,:]+[\"'“]|shared/research|findings\.md|anchors\.md")
    hits = []
    for pkg in SOURCES:
        for path in sorted((ROOT / pkg).rglob("*")):
            if path.suffix in (".py", ".h", ".cpp", ".cu", ".cuh", ".yaml") and path != Path(__file__):
                for n, line in enumerate(path.read_text().splitlines(), 1):
                    if bad.search(line):
                        hits.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert hits == []


def test_the_layout_names_every_bench_script_tool_and_the_command():
    """docs/README.md's layout names smgs_cli/ and each script of bench/ and tools/ (a new one is
    listed with what it is for, not left for a reader to find)."""
    text = (ROOT / "docs" / "README.md").read_text()
    layout = text[text.index("## Layout"):]
    scripts = [p for d in ("bench", "tools") for p in sorted((ROOT / d).glob("*.py")) if p.name != "__init__.py"]
    missing = [f"{p.parent.name}/{p.name}" for p in scripts if p.name not in layout]
    assert not missing and "smgs_cli/" in layout, missing
