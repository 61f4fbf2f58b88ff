"""Every measuring tool's ``--results FILE``: its section of the document is what it
printed, in Markdown, under the heading README links to, with the command that made it.

Each tool runs a tiny configuration here (seconds of flight, one round): the figures are
meaningless, the tests check the plumbing. tools/evidence.py and tools/long_run.py are
checked the same way in their own tests.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from tool_module import load_tool

TINY = {
    "speed": ("Speed", ["--seconds", "0.5", "--rounds", "1", "--rate", "200", "400"]),
    "online_overhead": ("Online overhead", ["--seconds", "0.5", "--rounds", "1"]),
    "turns": ("Tilt in turns", ["--seconds", "11", "--seeds", "1"]),
    "consistency": (
        "Consistency",
        ["--runs", "1", "--quick", "--scenario", "small", "--jobs", "1"],
    ),
    "start_in_motion": (
        "Start in motion",
        ["--scenario", "small", "--seeds", "0", "--starts", "0", "10"],
    ),
    "service_bench": (
        "Service",
        ["--only", "replay", "--replay-seconds", "1", "--rounds", "1"],
    ),
}


@pytest.mark.parametrize("name", list(TINY))
def test_the_section_is_the_printed_markdown(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    if name == "turns":
        pytest.importorskip("jsbsim", reason="jsbsim is needed for the simulated flights")
    title, arguments = TINY[name]
    results = tmp_path / "results.md"
    arguments = [*arguments, "--results", str(results)]
    assert load_tool(name).main(arguments) == 0
    out = capsys.readouterr().out
    anchor = title.lower().replace(" ", "-")
    section = results.read_text().split(f"<!-- BEGIN {anchor} -->\n", 1)[1]
    assert section.startswith(f"## {title}\n")
    assert f"Regenerate: `.venv/bin/python tools/{name}.py {' '.join(arguments)}`" in section
    assert f"\n\n{out.strip()}\n\n<!-- END {anchor} -->\n" in section
    # --results alone gives Markdown: a table whose header is apart from the text above
    lines = out.splitlines()
    delimiter = next(i for i, line in enumerate(lines) if line.startswith("|---"))
    assert lines[delimiter - 1].startswith("| ")
    assert delimiter == 1 or lines[delimiter - 2] == ""
