"""The one rule for where a run may write: never over what it reads.

Every command checks its outputs with :func:`check_outputs` before it opens
anything for writing, so that ``mavest replay f.tlog --out-tlog f.tlog`` (or the
same through a symbolic or hard link) leaves ``f.tlog`` untouched instead of
truncating the file it is reading. Two outputs on one path are refused as well
(the file would be neither), and so is an output whose folder does not exist:
mavest creates no folders a user did not ask for (``demo --output-dir`` and
``fleet --out-dir`` are the options that name a folder to make).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path


class OutputPathError(ValueError):
    """An output that would overwrite an input or another output, or has no folder."""


def _identity(path: Path) -> tuple[str, tuple[int, int] | None]:
    """The resolved path, and (device, inode) when the file exists (hard links)."""
    resolved = os.path.realpath(path)
    try:
        status = os.stat(resolved)
    except OSError:
        return resolved, None
    return resolved, (status.st_dev, status.st_ino)


def _same(a: tuple[str, tuple[int, int] | None], b: tuple[str, tuple[int, int] | None]) -> bool:
    return a[0] == b[0] or (a[1] is not None and a[1] == b[1])


def check_outputs(
    inputs: Mapping[str, str | Path | None], outputs: Mapping[str, str | Path | None]
) -> None:
    """Refuse (:class:`OutputPathError`) outputs that are inputs, each other, or have no
    folder to go in. Keys name the options (``"--out-tlog"``) for the message; a value of
    None is an option not given."""
    read = {name: _identity(Path(p)) for name, p in inputs.items() if p is not None}
    written: dict[str, tuple[str, tuple[int, int] | None]] = {}
    for name, given in outputs.items():
        if given is None:
            continue
        path = Path(given)
        identity = _identity(path)
        for input_name, input_identity in read.items():
            if _same(identity, input_identity):
                raise OutputPathError(f"{name} {path} is {input_name}: refusing to write over it")
        for other, other_identity in written.items():
            if _same(identity, other_identity):
                raise OutputPathError(f"{name} and {other} are both {path}: give each its own file")
        if os.path.isdir(identity[0]):
            raise OutputPathError(f"{name} {path} is a folder: name a file in it")
        folder = os.path.dirname(identity[0])
        if not os.path.isdir(folder):
            raise OutputPathError(f"{name} {path}: no folder {os.path.dirname(path) or '.'}")
        written[name] = identity


def partial_path(path: str | Path) -> Path:
    """Where a file is written before it is renamed to ``path`` (whole, at the end): a
    hidden file beside it, so that the rename cannot cross file systems, named after
    the process, so that two runs never write the same one."""
    path = Path(path)
    return path.with_name(f".{path.name}.{os.getpid()}.partial")


def write_atomically(path: str | Path, data: bytes) -> None:
    """Write a whole file or nothing: a run stopped half-way leaves the old file (or
    none), never a part (:func:`partial_path` until it is whole). A file replaced keeps
    its permissions; a new one gets what the umask gives any new file."""
    path = Path(path)
    temporary = partial_path(path)
    try:
        mode = path.stat().st_mode & 0o7777
    except FileNotFoundError:
        mode = None
    try:
        with temporary.open("wb") as stream:
            stream.write(data)
            stream.flush()
            os.fsync(stream.fileno())
        if mode is not None:
            os.chmod(temporary, mode)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
