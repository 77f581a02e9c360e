"""The repository cites only its own documents, and cites them right."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DESIGN = ROOT / "docs" / "design.md"
# Everything a reader of the repository reads: code, tests, benchmarks, docs, build files.
SOURCES = sorted(
    p
    for pattern in (
        "python/**/*.py",
        "python/**/*.pyi",
        "rust/**/*.rs",
        "tests/*.py",
        "benchmarks/*.py",
        "docs/**/*.md",
        "docs/**/*.py",
        "*.md",
        "*.toml",
        ".ci/*",
    )
    for p in ROOT.glob(pattern)
    if p.is_file() and "target" not in p.parts and p.name != "test_docs.py"
)
CITATION = re.compile(r"docs/design\.md,\s+(?:section\s+)?[\"'“]([^\"'”]+)[\"'”]")


def _headings() -> set[str]:
    return {
        m.group(1).strip()
        for m in re.finditer(r"^#{2,4}\s+(.+)$", DESIGN.read_text(), re.MULTILINE)
    }


def test_sources_found() -> None:
    assert DESIGN.is_file()
    assert len(SOURCES) > 50


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_cites_only_documents_inside_the_repository(path: Path) -> None:
    text = path.read_text(errors="replace")
    # The design document of the repository is docs/design.md; no other DESIGN.md, no
    # shared notes outside the repository.
    bad = [m.group(0) for m in re.finditer(r"\S*DESIGN\.md\S*", text)]
    bad += [m.group(0) for m in re.finditer(r"\.\./shared/(?!data\b)\S+", text)]
    assert not bad, f"{path.relative_to(ROOT)} cites {bad}"


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_design_citations_name_a_section(path: Path) -> None:
    text = " ".join(path.read_text(errors="replace").split())  # citations may wrap lines
    cited = {m.group(1).strip() for m in CITATION.finditer(text)} - {"<name>"}
    missing = sorted(cited - _headings())
    assert not missing, f"{path.relative_to(ROOT)} cites missing sections {missing}"


@pytest.mark.parametrize(
    "path",
    [p for p in SOURCES if p.suffix in (".py", ".rs", ".pyi") and "tests" not in p.parts],
    ids=lambda p: str(p.relative_to(ROOT)),
)
def test_code_cites_no_issue_number(path: Path) -> None:
    hits = re.findall(r"\bissues?\s+#?\d+", path.read_text(), re.IGNORECASE)
    assert not hits, f"{path.relative_to(ROOT)}: {hits}"
