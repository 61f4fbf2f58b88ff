"""What ``mavest fleet`` is given, as the list of logs to replay, in a fixed order.

Each argument is a log, a folder (its logs, in every sub-folder: .tlog, .bin and
.ulg files; hidden files are left out), or a glob (``flights/**/*.tlog``, expanded
by mavest, sorted, so that a shell that does not expand it gives the same list);
any of these as a local path or an fsspec URL (``s3://bucket/logs/``,
``memory://…``, ``file://…``). The order is the arguments', and within one the
sorted names; a log named twice is replayed once. A file of another suffix is a
log only when named on its own (its replay says what it is not).
"""

from __future__ import annotations

import glob
import os
from collections.abc import Sequence
from pathlib import Path

from mavest.fleet.rows import is_url, local_file
from mavest.paths import name_start

LOG_SUFFIXES = (".tlog", ".bin", ".ulg")


class FleetInputError(ValueError):
    """An argument that names no logs mavest can reach (one line)."""


def _is_log_name(name: str) -> bool:
    return not name.startswith(".") and name.lower().endswith(LOG_SUFFIXES)


def _folder_logs(folder: str) -> list[str]:
    found = []
    for root, folders, files in os.walk(folder):
        folders[:] = [f for f in folders if not f.startswith(".")]
        found += [
            os.path.normpath(os.path.join(root, name)) for name in files if _is_log_name(name)
        ]
    return sorted(found)


def _glob(pattern: str) -> list[str]:
    """What a glob matches, sorted. A ``**`` goes into sub-folders but not through a
    link to a folder (as a folder argument's walk does not): a link back up would make
    it endless. Hidden files and folders are not matched by a wildcard, as glob's."""
    if "**" not in pattern:
        return sorted(glob.glob(pattern))
    parts = Path(pattern).parts
    fixed = 0  # the leading parts without wildcards: where the walk starts
    while fixed < len(parts) and not glob.has_magic(parts[fixed]):
        fixed += 1
    start = Path(*parts[:fixed]) if fixed else Path()
    matches = []
    for match in start.glob(str(Path(*parts[fixed:]))):  # (pathlib: no links under **)
        if not any(part.startswith(".") for part in match.parts[len(start.parts) :]):
            matches.append(str(match))
    return sorted(matches)


def _local(argument: str) -> list[str]:
    if glob.has_magic(argument):
        matches = _glob(argument)
        logs: list[str] = []
        for match in matches:
            logs += _folder_logs(match) if os.path.isdir(match) else [match]
        return logs
    if os.path.isdir(argument):
        return _folder_logs(argument)
    return [argument]  # a file, or not: its row says so


def _remote(argument: str) -> list[str]:
    try:
        import fsspec
    except ImportError:
        raise FleetInputError(
            f"{argument}: URLs need fsspec: pip install 'mavest[fleet]'"
        ) from None
    try:
        fs, path = fsspec.core.url_to_fs(argument)
    except ImportError as error:  # the protocol's backend is not installed
        raise FleetInputError(f"{argument}: {error}") from None
    except ValueError as error:  # no such protocol
        raise FleetInputError(f"{argument}: {error}") from None
    try:
        if glob.has_magic(path):
            matches = sorted(fs.glob(path))
        else:
            matches = [path]
        logs: list[str] = []
        for match in matches:
            if fs.isdir(match):
                inside = sorted(fs.find(match))
                logs += [fs.unstrip_protocol(p) for p in inside if _is_log_name(p.rsplit("/")[-1])]
            else:
                logs.append(argument if match == path else fs.unstrip_protocol(match))
    except OSError as error:
        raise FleetInputError(f"{argument}: {error}") from None
    return logs


def expand(arguments: Sequence[str]) -> tuple[list[str], list[str]]:
    """The logs the arguments name, in order, each once; and a line for each argument
    that named none (a glob that matches nothing, a folder without logs)."""
    logs: list[str] = []
    seen: set[str] = set()
    empty: list[str] = []
    for argument in arguments:
        found = _remote(argument) if is_url(argument) else _local(argument)
        if not found:
            empty.append(f"{argument}: no .tlog, .bin or .ulg log there")
        for name in found:
            identity = name if is_url(name) else os.path.realpath(name)
            if identity not in seen:
                seen.add(identity)
                logs.append(name)
    return logs, empty


def local_paths(logs: Sequence[str]) -> list[Path]:
    """The logs that are files here (paths, and ``file://`` URLs: what they name is read
    as any other file), for the check that no output is one."""
    return [path for path in map(local_file, logs) if path is not None]


# A log's output names must be file names (at most 255 bytes) with the longest suffix
# and a count: NAME-999.estimates.parquet. A longer log name gives its start.
_LONGEST_STEM = 255 - len("-999.estimates.parquet")


def output_names(logs: Sequence[str]) -> list[str]:
    """Each log's name for its own outputs in ``--out-dir``: its file name without the
    suffix (its first 233 bytes), and for a later log of a name taken already (``a/flight.tlog``,
    ``b/flight.tlog``, ``flight.bin``) that name and ``-2``, ``-3`` …: in the order of the
    logs, so the same logs give the same names. Names are compared ignoring case (a
    folder may)."""
    taken: set[str] = set()
    names = []
    for log_name in logs:
        stem = log_name.rstrip("/").rsplit("/", 1)[-1].rsplit(os.sep, 1)[-1]
        stem = stem.rsplit(".", 1)[0] if "." in stem[1:] else stem
        stem = name_start(stem, _LONGEST_STEM)
        name, n = stem, 1
        while name.lower() in taken:
            n += 1
            name = f"{stem}-{n}"
        taken.add(name.lower())
        names.append(name)
    return names
