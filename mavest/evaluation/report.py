"""docs/results.md: each section written by the tool that measures it, never by hand.

A section lies between ``<!-- BEGIN name -->`` and ``<!-- END name -->``, where ``name``
is the anchor its heading gets on GitHub (``## Long runs`` → ``#long-runs``), so that
links to the document keep pointing at the right table. :func:`write_section` replaces
one section and leaves every other byte of the file as it was; the section says when
and on what it was measured and the command that regenerates it. What a tool prints is
what it writes: :func:`teed_stdout` keeps a copy of the printed tables while they still
reach the terminal.

The tools take ``--results [FILE]`` (:func:`add_results_option`) to write their section.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import os
import platform
import re
import shlex
import statistics
import sys
from collections.abc import Iterator, Sequence
from importlib import metadata
from pathlib import Path

import mavest
from mavest.paths import write_atomically

#: The document of a clone: tools run from one, next to ``docs/``.
RESULTS = Path(mavest.__file__).resolve().parents[1] / "docs" / "results.md"

#: The sections in the order the document shows them, whichever tool runs first; a
#: section not named here goes after them.
SECTIONS = (
    "Accuracy",
    "Smoothing",
    "Consistency",
    "Smoothing consistency",
    "Covariance on real data",
    "Cross-validation",
    "Tilt in turns",
    "Speed",
    "Online overhead",
    "Service",
    "Replay time split",
    "Long runs",
    "Onboard logs",
    "Fleet",
)

HEADER = """\
# Results

Every table below is printed by the tool that measures it and written here by the same
run (`--results`); none is edited by hand. Each section says when, on what machine and
with which mavest it was measured, and the command that regenerates it. Earlier figures
are in git's history of this file.
"""

_BEGIN = "<!-- BEGIN {} -->"
_END = "<!-- END {} -->"


def anchor(title: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces → '-'."""
    return re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")


def machine_description() -> str:
    """One line: CPU model and cores, the OS, Python and the numeric libraries' versions."""
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):  # Linux names the model; elsewhere the architecture
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    versions = []
    for package in ("numpy", "numba"):
        try:
            versions.append(f"{package} {metadata.version(package)}")
        except metadata.PackageNotFoundError:
            versions.append(f"no {package}")
    return ", ".join(
        [
            f"{cpu} ({os.cpu_count()} cores)",
            f"{platform.system()} {platform.machine()}",
            f"Python {platform.python_version()}",
            *versions,
        ]
    )


def command_line(tool: str | os.PathLike[str], argv: Sequence[str] | None = None) -> str:
    """The command that runs ``tool`` (a file under tools/) with ``argv`` (default: this
    process's own arguments), as a user types it from the project's root."""
    arguments = list(sys.argv[1:] if argv is None else argv)
    script = f"tools/{Path(tool).name}"
    return shlex.join([".venv/bin/python", script, *arguments])


def stamp(command: str, day: datetime.date | None = None, machine: str | None = None) -> str:
    """The lines under a section's heading: when, with which mavest, on what, and how again."""
    day = day or datetime.date.today()
    machine = machine or machine_description()
    return (
        f"Measured {day.isoformat()}, mavest {mavest.__version__}, {machine}.\n\n"
        f"Regenerate: `{command}`"
    )


def paired(ours: Sequence[float], theirs: Sequence[float], unit: str = "°") -> str:
    """A paired comparison per trial, as the tables say it (lower is better): "better
    on k of n, median difference d°"."""
    differences = [a - b for a, b in zip(ours, theirs, strict=True)]
    better = sum(d < 0 for d in differences)
    median = statistics.median(differences)
    return f"better on {better} of {len(differences)}, median difference {median:+.3f}{unit}"


def tool_parser(doc: str) -> argparse.ArgumentParser:
    """A tool's argument parser from its module docstring, which opens with a line that
    says what the tool does and a blank line: that line is the description, the rest
    the epilog (usage, what it measures, how), shown by ``--help`` as written."""
    title, _, rest = doc.partition("\n\n")
    return argparse.ArgumentParser(
        description=title, formatter_class=argparse.RawDescriptionHelpFormatter, epilog=rest
    )


def progress(tool: str, line: str) -> None:
    """A line of a tool's progress or refusal, on stderr: "tool: line"."""
    print(f"{tool}: {line}", file=sys.stderr, flush=True)


def add_results_option(parser: argparse.ArgumentParser) -> None:
    """``--results [FILE]``, the same in every tool."""
    parser.add_argument(
        "--results",
        type=Path,
        nargs="?",
        const=RESULTS,
        metavar="FILE",
        help="also write what is printed (as Markdown) as this tool's section of FILE "
        "(default: docs/results.md), stamped with the date, version, machine and command",
    )


def add_config_option(parser: argparse.ArgumentParser, what: str) -> None:
    """``--config FILE``, repeatable: ``what`` the tool does with each configuration
    file (TOML, as the service reads it)."""
    parser.add_argument(
        "--config", action="append", type=Path, default=[], metavar="FILE", help=what
    )


@contextlib.contextmanager
def teed_stdout() -> Iterator[io.StringIO]:
    """Everything printed within still goes to stdout, and is kept in the yielded buffer."""
    kept = io.StringIO()
    terminal = sys.stdout

    class Tee(io.TextIOBase):
        def write(self, text: str) -> int:
            kept.write(text)
            return terminal.write(text)

        def flush(self) -> None:
            terminal.flush()

    with contextlib.redirect_stdout(Tee()):
        yield kept


@contextlib.contextmanager
def results_section(
    path: str | os.PathLike[str] | None,
    title: str,
    tool: str | os.PathLike[str],
    argv: Sequence[str] | None,
    doc: str | None = None,
) -> Iterator[None]:
    """What is printed within becomes the section ``title`` of ``path`` (nothing is kept
    when ``path`` is None, and nothing written when the block raises), stamped with the
    command ``tool`` ``argv`` and described by the first line of ``doc`` (the tool's
    docstring). A section that cannot be written ends the tool with one line and
    status 1 (SystemExit)."""
    if path is None:
        yield
        return
    with teed_stdout() as printed:
        yield
    description = doc.strip().split("\n")[0] if doc else ""
    try:
        write_section(path, title, printed.getvalue(), command_line(tool, argv), description)
    except (OSError, ValueError) as error:
        # the tables are on the terminal already; one line says why they are not in the file
        raise SystemExit(f"could not write the section {title!r} of {path}: {error}") from None
    print(f"wrote the section {title!r} of {path}", file=sys.stderr)


def render_section(
    title: str,
    body: str,
    command: str,
    description: str = "",
    day: datetime.date | None = None,
    machine: str | None = None,
) -> str:
    """A whole section, markers included, ending in a newline."""
    name = anchor(title)
    if not body.strip():
        raise ValueError(f"nothing to write in the section {name!r}")
    parts = [f"## {title}"]
    if description:
        parts.append(description.strip())
    parts += [stamp(command, day, machine), body.strip("\n")]
    text = "\n\n".join(parts)
    if _BEGIN.format(name) in text or _END.format(name) in text:
        raise ValueError(f"the section {name!r} cannot contain its own markers")
    # a blank line before the end marker: nothing of the body's last table runs into it
    return f"{_BEGIN.format(name)}\n{text}\n\n{_END.format(name)}\n"


def _span(text: str, name: str) -> tuple[int, int] | None:
    """Where the section ``name`` lies in ``text`` (markers and the end marker's newline
    included), or None; ValueError when its markers are not one well-formed pair."""
    begin, end = _BEGIN.format(name), _END.format(name)
    starts, ends = text.count(begin), text.count(end)
    if starts == ends == 0:
        return None
    if starts != 1 or ends != 1 or text.index(begin) > text.index(end):
        raise ValueError(f"the markers of section {name!r} are not one BEGIN then one END")
    start, stop = text.index(begin), text.index(end) + len(end)
    if text.startswith("\n", stop):
        stop += 1
    return start, stop


def _insertion_point(text: str, name: str) -> tuple[int, str]:
    """Where a new section ``name`` goes (before the first present section that
    :data:`SECTIONS` puts after it, else at the end) and what separates it from the
    text before."""
    order = [anchor(title) for title in SECTIONS]
    later = order[order.index(name) + 1 :] if name in order else []
    starts = [text.index(_BEGIN.format(other)) for other in later if _BEGIN.format(other) in text]
    if starts:
        return min(starts), ""
    return len(text), "" if text.endswith("\n\n") else ("\n" if text.endswith("\n") else "\n\n")


def write_section(
    path: str | os.PathLike[str],
    title: str,
    body: str,
    command: str,
    description: str = "",
    day: datetime.date | None = None,
    machine: str | None = None,
) -> None:
    """Replace (or add) the section ``title`` of the document at ``path`` with ``body``,
    stamped; the rest of the file is kept byte for byte. The file is replaced at once
    (written beside it, then renamed): a reader, or a run that fails half-way, sees the
    old document or the new one, never a part. A new file starts with :data:`HEADER`.
    """
    path = Path(path)
    section = render_section(title, body, command, description, day, machine)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        text = HEADER
    name = anchor(title)
    span = _span(text, name)
    if span is not None:
        start, stop = span
        new = text[:start] + section + text[stop:]
    else:
        at, separator = _insertion_point(text, name)
        after = "\n" if at < len(text) else ""  # a blank line before the next section
        new = text[:at] + separator + section + after + text[at:]
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, new.encode("utf-8"))
