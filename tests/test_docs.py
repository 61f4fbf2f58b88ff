"""The documents read as they were written: plain text a reader's viewer shows whole,
the README within its length, and every results table made by a tool that is here."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

PROJECT = Path(__file__).resolve().parents[1]
DOCUMENTS = sorted([PROJECT / "README.md", PROJECT / "CHANGELOG.md", *PROJECT.glob("docs/*.md")])
README_LINES = 400  # a newcomer's page: measured tables go to docs/results.md


@pytest.mark.parametrize("path", DOCUMENTS, ids=lambda p: p.name)
def test_no_control_characters(path: Path) -> None:
    # (a TeX macro written into a Python string, "\tau", became a tab and "au")
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        bad = [hex(ord(c)) for c in line if ord(c) < 0x20 or ord(c) == 0x7F]
        assert not bad, f"{path.name}:{number}: control characters {bad}"


def test_readme_fits_its_length() -> None:
    lines = (PROJECT / "README.md").read_text(encoding="utf-8").count("\n")
    assert lines <= README_LINES, f"README.md has {lines} lines, over {README_LINES}"


def test_every_results_section_names_a_tool_that_is_here() -> None:
    text = (PROJECT / "docs" / "results.md").read_text(encoding="utf-8")
    tools = re.findall(r"^Regenerate: `(?:\.venv/bin/python )?(tools/[\w./]+\.py)", text, re.M)
    sections = re.findall(r"^## ", text, re.M)
    assert len(tools) == len(sections), "a section without its Regenerate line"
    missing = sorted({tool for tool in tools if not (PROJECT / tool).is_file()})
    assert not missing, missing
