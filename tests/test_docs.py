"""The README and docs/: short lines, links that resolve (files and headings), no link to the archived notebook as
current."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]  # the working docs; docs/archive/ is history


def slug(heading: str) -> str:
    """GitHub's anchor for a Markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """The anchors of a Markdown file's headings, outside fenced blocks."""
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    return {slug(m) for m in re.findall(r"^#+ (.+)$", text, flags=re.M)}


def test_slug_matches_githubs_anchors():
    assert slug("5. The interactive step (`mpc=interactive`)") == "5-the-interactive-step-mpcinteractive"
    assert slug("Gradients: the surrogate (the paper's Remark 3)") == "gradients-the-surrogate-the-papers-remark-3"


@pytest.mark.parametrize("path", DOCS, ids=lambda p: p.name)
def test_every_relative_link_resolves_to_a_file_and_heading(path):
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    links = re.findall(r"\]\(([^)\s]+)\)", text)
    assert links
    for link in links:
        if re.match(r"[a-z]+://", link):
            continue
        target, _, anchor = link.partition("#")
        file = (path.parent / target).resolve() if target else path
        assert file.exists(), f"{path.name}: {link}"
        if anchor and file.suffix == ".md":
            assert anchor in anchors(file), f"{path.name}: {link}"


def test_readme_reads_in_ten_minutes():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 170 and max(map(len, lines)) <= 120
    assert not [line for line in lines if "studies" in line]  # the findings are in docs/findings.md
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")


def test_the_archived_notebook_is_linked_only_as_history():
    for path in DOCS:
        for line in path.read_text().splitlines():
            if "archive/" in line:
                assert re.search(r"notebook|history|not current", line), f"{path.name}: {line}"
