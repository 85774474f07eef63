"""The user documents: README.md stays short, and every relative link of README.md and doc/*.md
leads to a file of the repository and, with a #fragment, to one of its headings."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCUMENTS = [REPO / "README.md", *sorted((REPO / "doc").glob("*.md"))]
#: how-tos written in parallel branches (calibration); links to them are kept in the README
#: while those branches land
PENDING = {"doc/calibration.md", "doc/calibration_board.md"}

_LINK = re.compile(r"\]\(([^)\s#]*)(#[^)\s]+)?\)")


def github_anchor(heading: str) -> str:
    """The fragment GitHub gives a markdown heading: lower case, punctuation other than '-'
    and '_' removed, spaces as '-'."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    lines = path.read_text(encoding="utf-8").splitlines()
    in_code = False
    out = set()
    for line in lines:
        if line.startswith("```"):
            in_code = not in_code
        elif not in_code and line.startswith("#"):
            out.add(github_anchor(line.lstrip("#")))
    return out


def test_readme_is_at_most_400_lines() -> None:
    lines = (REPO / "README.md").read_text(encoding="utf-8").count("\n")
    assert lines <= 400, f"README.md has {lines} lines: move details into doc/"


def test_readme_starts_with_the_two_commands() -> None:
    """make demo and make test are the first commands a reader sees (.ci/run runs make test)."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    first_block = text.split("```bash\n", 1)[1].split("```", 1)[0].splitlines()
    assert [line.split()[:2] for line in first_block] == [["make", "demo"], ["make", "test"]]


@pytest.mark.parametrize("doc", DOCUMENTS, ids=lambda p: str(p.relative_to(REPO)))
def test_relative_links_resolve(doc: Path) -> None:
    broken = []
    for m in _LINK.finditer(doc.read_text(encoding="utf-8")):
        target, fragment = m.group(1), m.group(2)
        if target.startswith(("http://", "https://", "mailto:")):
            continue
        path = (doc.parent / target).resolve() if target else doc
        rel = path.relative_to(REPO).as_posix() if path.is_relative_to(REPO) else str(path)
        if not path.exists():
            if rel not in PENDING:
                broken.append(f"{target}: no such file")
            continue
        if fragment and path.suffix == ".md" and fragment[1:] not in _anchors(path):
            broken.append(f"{target}{fragment}: no such heading in {rel}")
    assert not broken, broken


def test_github_anchor_matches_github() -> None:
    assert github_anchor(" 9.6 For monocular frontends (off by default = the paper)") == \
        "96-for-monocular-frontends-off-by-default--the-paper"
    assert github_anchor("Foxglove view, TRC/C3D/CSV export") == "foxglove-view-trcc3dcsv-export"
