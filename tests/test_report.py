"""docs/results.md's sections: replaced in place, the rest of the file untouched, written
at once, stamped, and in the document's order whichever tool writes first."""

from __future__ import annotations

import datetime
import os
import re
import stat
from pathlib import Path

import pytest

import mavest
from mavest.evaluation import report

DAY = datetime.date(2024, 5, 17)
MACHINE = "Test CPU (2 cores), Linux x86_64, Python 3.11.0, numpy 2.0.0, numba 0.60.0"
TABLE = "| a | b |\n|---|---|\n| 1 | 2 |\n"


def write(path: Path, title: str, body: str = TABLE, command: str = "tool --flag") -> None:
    report.write_section(path, title, body, command, "What it measures.", DAY, MACHINE)


def section_of(text: str, name: str) -> str:
    match = re.search(rf"<!-- BEGIN {name} -->\n.*?<!-- END {name} -->\n", text, re.DOTALL)
    assert match is not None, name
    return match.group(0)


def test_a_new_file_gets_the_header_and_a_stamped_section(tmp_path: Path) -> None:
    path = tmp_path / "docs" / "results.md"
    write(path, "Long runs", command=".venv/bin/python tools/long_run.py --results")
    text = path.read_text()
    assert text.startswith(report.HEADER)
    section = section_of(text, "long-runs")
    assert section.splitlines()[1] == "## Long runs"
    assert "What it measures." in section
    assert (
        f"Measured 2024-05-17, mavest {mavest.__version__}, {MACHINE}.\n\n"
        "Regenerate: `.venv/bin/python tools/long_run.py --results`"
    ) in section
    assert TABLE in section
    assert text.endswith("<!-- END long-runs -->\n")


def test_replacing_a_section_keeps_every_other_byte(tmp_path: Path) -> None:
    path = tmp_path / "results.md"
    write(path, "Accuracy")
    write(path, "Speed")
    # a hand-written line between the sections, and text after the last, stay as they are
    text = path.read_text().replace("<!-- BEGIN speed -->", "A note.\n\n<!-- BEGIN speed -->")
    path.write_text(text + "\nTrailing words, no newline")
    before = path.read_bytes()
    old = section_of(before.decode(), "accuracy").encode()

    write(path, "Accuracy", "| new |\n|---|\n| 3 |\n", "tool --again")
    after = path.read_bytes()
    new = section_of(after.decode(), "accuracy").encode()
    assert b"| new |" in new and b"tool --again" in new and TABLE.encode() not in new
    start = before.index(old)
    assert after[:start] == before[:start]
    assert after[start + len(new) :] == before[start + len(old) :]


def test_a_new_section_goes_where_the_document_order_puts_it(tmp_path: Path) -> None:
    path = tmp_path / "results.md"
    write(path, "Long runs")
    write(path, "Accuracy")
    write(path, "Speed")
    write(path, "Something else")  # not in the order: after everything
    text = path.read_text()
    names = re.findall(r"<!-- BEGIN ([\w-]+) -->", text)
    assert names == ["accuracy", "speed", "long-runs", "something-else"]
    # sections are separated by one blank line, whatever the order they were written in
    assert "-->\n\n<!-- BEGIN" in text and "-->\n<!-- BEGIN" not in text
    assert "\n\n\n" not in text


def test_the_anchors_are_the_headings_github_links_to() -> None:
    assert report.anchor("Long runs") == "long-runs"
    assert report.anchor("Tilt in turns") == "tilt-in-turns"
    assert report.anchor("Accuracy") == "accuracy"
    anchors = {report.anchor(title) for title in report.SECTIONS}
    assert {"accuracy", "consistency", "speed", "service", "long-runs"} <= anchors


def test_a_failed_write_leaves_the_old_file_and_no_temporary(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "results.md"
    write(path, "Accuracy")
    before = path.read_bytes()

    def refuse(source: str, target: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(report.os, "replace", refuse)
    with pytest.raises(OSError, match="disk full"):
        write(path, "Accuracy", "| other |\n")
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.md"]


def test_the_file_keeps_its_permissions(tmp_path: Path) -> None:
    path = tmp_path / "results.md"
    write(path, "Accuracy")
    os.chmod(path, 0o640)
    write(path, "Speed")
    assert stat.S_IMODE(path.stat().st_mode) == 0o640


@pytest.mark.parametrize(
    "broken",
    [
        "<!-- BEGIN accuracy -->\nno end\n",
        "<!-- END accuracy -->\n<!-- BEGIN accuracy -->\n",
        "<!-- BEGIN accuracy -->\n<!-- END accuracy -->\n<!-- BEGIN accuracy -->\n",
    ],
)
def test_broken_markers_are_refused_and_the_file_left_alone(tmp_path: Path, broken: str) -> None:
    path = tmp_path / "results.md"
    path.write_text(broken)
    with pytest.raises(ValueError, match="accuracy"):
        write(path, "Accuracy")
    assert path.read_text() == broken


@pytest.mark.parametrize("body", ["", "\n  \n", "<!-- END accuracy -->\n"])
def test_a_body_that_cannot_be_a_section_is_refused(tmp_path: Path, body: str) -> None:
    with pytest.raises(ValueError, match="accuracy"):
        write(tmp_path / "results.md", "Accuracy", body)
    assert not (tmp_path / "results.md").exists()


def test_the_machine_is_described_in_one_line() -> None:
    line = report.machine_description()
    assert "\n" not in line
    assert re.fullmatch(
        r".+ \(\d+ cores\), \w+ \w+, Python \d+\.\d+\.\d+, numpy \S+, numba \S+", line
    ), line


def test_the_command_is_what_a_user_types() -> None:
    command = report.command_line("/anywhere/tools/evidence.py", ["--trials", "02 07", "--quick"])
    assert command == ".venv/bin/python tools/evidence.py --trials '02 07' --quick"


def test_what_is_printed_is_what_is_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "results.md"
    with report.results_section(path, "Speed", "tools/speed.py", ["--results"], "Speed.\n\nMore"):
        print(TABLE, end="")
    assert capsys.readouterr().out == TABLE  # still on the terminal
    section = section_of(path.read_text(), "speed")
    assert TABLE in section
    assert "\nSpeed.\n" in section and "More" not in section
    assert "Regenerate: `.venv/bin/python tools/speed.py --results`" in section


def test_nothing_is_written_without_a_file_or_after_a_failure(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with report.results_section(None, "Speed", "tools/speed.py", []):
        print("printed only")
    assert capsys.readouterr().out == "printed only\n"
    path = tmp_path / "results.md"
    with (
        pytest.raises(RuntimeError),
        report.results_section(path, "Speed", "tools/speed.py", []),
    ):
        print(TABLE)
        raise RuntimeError("measurement failed")
    assert not path.exists()


def test_a_section_that_cannot_be_written_ends_the_tool_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "results.md"
    path.write_text("<!-- BEGIN speed -->\nno end\n")
    with (
        pytest.raises(SystemExit, match=r"could not write the section 'Speed' of .*results.md"),
        report.results_section(path, "Speed", "tools/speed.py", []),
    ):
        print(TABLE)
    assert capsys.readouterr().out == TABLE + "\n"  # the table still reached the terminal
    assert path.read_text() == "<!-- BEGIN speed -->\nno end\n"
