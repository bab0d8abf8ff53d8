"""The documentation stays short, whole and true to the tree.

README.md is the front page: what dcrad is, the two fresh-machine commands and a few
examples; the rest lives in docs/guide.md (using it) and docs/design.md (how it works).
These tests keep that split from eroding: the README has a hard length limit, every
relative link and image in README.md and docs/*.md must resolve (a renamed file or
heading breaks a link silently otherwise), and the design guide's module map must name
every module, found on disk, so a new module without a line there fails here.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DESIGN = ROOT / "docs" / "design.md"
DOCS = [README, *sorted((ROOT / "docs").glob("*.md"))]

#: the README's hard limit in lines: past it, material belongs in docs/guide.md or docs/design.md
README_MAX_LINES = 150

#: packages whose modules the module map must list (all the installed ones: pyproject.toml)
MAPPED_PACKAGES = ("dcrad", "coordinator", "worker", "scenes")

# [text](target) and ![alt](target), target without spaces, optionally followed by a "title"
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)
CODE_SPAN = re.compile(r"`[^`\n]*`")


def prose(path: Path) -> str:
    """The markdown of ``path`` without fenced code blocks and code spans (links there are not links)."""
    return CODE_SPAN.sub("", FENCE.sub("", path.read_text()))


def slug(heading: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = heading.strip().lower().replace("`", "")
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """The anchors of ``path``'s headings (outside code blocks), with GitHub's -1, -2 for repeats."""
    seen: dict[str, int] = {}
    out = set()
    for line in FENCE.sub("", path.read_text()).splitlines():
        m = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        s = slug(m.group(1))
        n = seen.get(s, 0)
        seen[s] = n + 1
        out.add(s if n == 0 else f"{s}-{n}")
    return out


def relative_links(path: Path) -> list[str]:
    return [t for t in LINK.findall(prose(path)) if not re.match(r"[a-z][a-z0-9+.-]*:", t, re.I)]


def modules() -> list[str]:
    """Every hand-written module of the mapped packages, as a path from the repository root."""
    found = []
    for pkg in MAPPED_PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            # a package's __init__.py speaks for the package, and the protobuf code is generated
            # (`make proto`; the map has one line for dcrad/v1/)
            if f.name == "__init__.py" or "_pb2" in f.name:
                continue
            found.append(f.relative_to(ROOT).as_posix())
    return found


def test_readme_is_short():
    n = len(README.read_text().splitlines())
    assert n <= README_MAX_LINES, (
        f"README.md has {n} lines, the limit is {README_MAX_LINES}: move details to docs/guide.md "
        f"(using dcrad) or docs/design.md (how it works)")


def test_readme_gives_the_fresh_machine_commands():
    text = README.read_text()
    for command in ("make demo", "make test"):
        assert command in text, f"README.md does not mention `{command}`"


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_resolve(doc):
    broken = []
    for target in relative_links(doc):
        file, _, anchor = target.partition("#")
        dest = (doc.parent / file).resolve() if file else doc
        if not dest.exists():
            broken.append(f"{target}: no file {dest.relative_to(ROOT) if dest.is_relative_to(ROOT) else dest}")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading with anchor #{anchor}")
        elif not dest.is_relative_to(ROOT):
            broken.append(f"{target}: outside the repository")
    assert not broken, f"{doc.relative_to(ROOT)}: broken links:\n  " + "\n  ".join(broken)


def test_docs_have_links_to_check():
    # the link pattern above must keep finding the README's images and guide links
    targets = relative_links(README)
    assert "docs/guide.md" in targets and "docs/design.md" in targets
    assert any(t.endswith(".png") for t in targets)


def test_module_map_names_every_module():
    text = DESIGN.read_text()
    assert "## Module map" in text
    section = text.split("## Module map", 1)[1]
    mods = modules()
    assert len(mods) > 30, mods  # the discovery itself works
    missing = [m for m in mods if f"`{m}`" not in section]
    assert not missing, ("docs/design.md's module map has no line for: " + ", ".join(missing)
                         + " (add one line each saying what the module holds)")


def test_module_map_has_no_stale_lines():
    # a module renamed or removed leaves a stale line; every `pkg/x.py` named must exist
    section = DESIGN.read_text().split("## Module map", 1)[1]
    packages = "|".join(MAPPED_PACKAGES)
    named = re.findall(rf"`((?:{packages})/[\w/]+\.py)`", section)
    stale = [m for m in named if not (ROOT / m).exists()]
    assert not stale, f"docs/design.md's module map names modules that do not exist: {stale}"
