"""The one rule for where a run may write: never over what it reads, nor over a file
it could not finish.

Every command checks its outputs with :func:`check_outputs` before it opens
anything for writing, so that ``mavest replay f.tlog --out-tlog f.tlog`` (or the
same through a symbolic or hard link) leaves ``f.tlog`` untouched instead of
truncating the file it is reading. Two outputs on one path are refused as well
(the file would be neither), and so is an output whose folder does not exist:
mavest creates no folders a user did not ask for (``demo --output-dir`` and
``fleet --out-dir`` are the options that name a folder to make). Each output is
also tried for writing before any is opened (a file made and removed in its
folder): a run refused for its third output has not emptied the first two.

What an output path names is written, never replaced: a symbolic link is written
at the file it points to; a character device or a FIFO (``/dev/stdout``, a pipe
made with ``mkfifo``) is written into as a stream (:func:`writes_in_place`). A
block device or a socket is refused: a table written over a disk would destroy its
file system, and a socket cannot be opened as a file.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import stat
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path


class OutputPathError(ValueError):
    """An output that would overwrite an input or another output, has no folder, or
    cannot be written."""


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


def _kind(path: str | Path) -> int | None:
    """The file type (``stat.S_IFMT``) of what ``path`` names, its links followed; None
    if nothing is there. (``os.stat`` on the path as given: ``/dev/stdout`` is a link
    through ``/proc`` that resolves to no path when it is a pipe, but stats as one.)"""
    try:
        return stat.S_IFMT(os.stat(path).st_mode)
    except OSError:
        return None


def writes_in_place(path: str | Path) -> bool:
    """Whether the output ``path`` is written straight into what is there, as a stream:
    a character device or a FIFO. No rename can make such a write atomic (and a rename
    would replace the device node with a file): a run stopped half-way has written
    part of it, as a program writing to a pipe does."""
    return _kind(path) in (stat.S_IFCHR, stat.S_IFIFO)


def output_target(path: str | Path) -> Path:
    """The file an output at ``path`` is written at: its symbolic links resolved (a link
    stays a link to the file written)."""
    return Path(os.path.realpath(path))


# The longest file name a Linux file system takes (bytes; ext4, XFS, btrfs, tmpfs).
_NAME_MAX = 255


def name_start(name: str, size: int) -> str:
    """The start of a file name that is at most ``size`` bytes, of whole characters (a
    name is bytes: its non-UTF-8 bytes, escaped in the text, are kept as they are)."""
    data = os.fsencode(name)
    end = min(size, len(data))
    while 0 < end < len(data) and data[end] & 0xC0 == 0x80:  # (inside a character)
        end -= 1
    return os.fsdecode(data[:end])


def _hidden_name(name: str, kind: str, pid: int | None = None) -> str:
    """The name of mavest's own file beside the file ``name`` (``kind``: probe, partial):
    hidden, the process's (``pid``, by default this one's), and never longer than a file
    name may be: a name near the limit keeps its start and a digest of the whole, so
    that its file is still its own."""
    tail = f".{os.getpid() if pid is None else pid}.{kind}"
    hidden = f".{name}{tail}"
    if len(os.fsencode(hidden)) <= _NAME_MAX:
        return hidden
    digest = hashlib.sha256(os.fsencode(name)).hexdigest()[:16]
    room = _NAME_MAX - len(tail) - len(digest) - 2  # ("." before, "~" between)
    return f".{name_start(name, room)}~{digest}{tail}"


def _check_writable(name: str, path: Path, target: str) -> None:
    """Refuse (:class:`OutputPathError`) an output that could not be written: a block
    device, a socket, a file or folder without write permission (or on a read-only
    file system)."""
    kind = _kind(path)
    if kind == stat.S_IFBLK:
        raise OutputPathError(f"{name} {path} is a block device: name a file")
    if kind == stat.S_IFSOCK:
        raise OutputPathError(f"{name} {path} is a socket: name a file")
    if kind is not None and not os.access(path, os.W_OK):
        raise OutputPathError(f"{name} {path}: cannot write it: permission denied")
    if kind in (stat.S_IFCHR, stat.S_IFIFO):
        return  # written in place: nothing is made beside it
    # a regular file (or none yet) is written beside itself and renamed: try the folder
    folder = os.path.dirname(target)
    probe = os.path.join(folder, _hidden_name(os.path.basename(target), "probe"))
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    except OSError as error:
        raise OutputPathError(
            f"{name} {path}: cannot write in {os.path.dirname(path) or '.'}: "
            f"{error.strerror or error}"
        ) from None
    with contextlib.suppress(OSError):
        os.unlink(probe)


class InputFiles:
    """The files a run reads, by resolved path and by (device, inode), so that each of
    many outputs is checked against all of them at once (``mavest fleet``: thousands of
    logs, two outputs each)."""

    def __init__(self, inputs: Mapping[str, str | Path | None]) -> None:
        self._by_path: dict[str, str] = {}
        self._by_inode: dict[tuple[int, int], str] = {}
        for name, given in inputs.items():
            if given is not None:
                path, inode = _identity(Path(given))
                self._by_path.setdefault(path, name)
                if inode is not None:
                    self._by_inode.setdefault(inode, name)

    def named(self, identity: tuple[str, tuple[int, int] | None]) -> str | None:
        """The name of the input that is the file of this identity, if one is."""
        path, inode = identity
        found = self._by_path.get(path)
        if found is None and inode is not None:
            found = self._by_inode.get(inode)
        return found


def check_outputs(
    inputs: Mapping[str, str | Path | None] | InputFiles,
    outputs: Mapping[str, str | Path | None],
) -> None:
    """Refuse (:class:`OutputPathError`) outputs that are inputs, each other, have no
    folder to go in, or cannot be written there. Keys name the options
    (``"--out-tlog"``) for the message; a value of None is an option not given."""
    read = inputs if isinstance(inputs, InputFiles) else InputFiles(inputs)
    written: dict[str, tuple[str, tuple[int, int] | None]] = {}
    for name, given in outputs.items():
        if given is None:
            continue
        path = Path(given)
        identity = _identity(path)
        input_name = read.named(identity)
        if input_name is not None:
            raise OutputPathError(f"{name} {path} is {input_name}: refusing to write over it")
        for other, other_identity in written.items():
            if _same(identity, other_identity):
                raise OutputPathError(f"{name} and {other} are both {path}: give each its own file")
        if os.path.isdir(identity[0]):
            raise OutputPathError(f"{name} {path} is a folder: name a file in it")
        folder = os.path.dirname(identity[0])
        if not os.path.isdir(folder) and not writes_in_place(path):
            if os.path.islink(path):  # (the folder missing is the one the link leads into)
                raise OutputPathError(f"{name} {path} links to {identity[0]}: no folder {folder}")
            raise OutputPathError(f"{name} {path}: no folder {os.path.dirname(path) or '.'}")
        written[name] = identity
    # only once every output is known good: a probe is a file made, if briefly
    for name, given in outputs.items():
        if given is not None:
            _check_writable(name, Path(given), written[name][0])


def partial_path(path: str | Path, pid: int | None = None) -> Path:
    """Where a file is written before it is published at ``path`` (:func:`publish`,
    whole, at the end), named after the process (``pid``: another's, by default this
    one), so that two runs never write the same one: a hidden file beside the file
    ``path`` resolves to, so that the rename cannot cross file systems; for an output
    written in place (:func:`writes_in_place`), in the temporary folder, whence it is
    copied."""
    target = output_target(path)
    folder = Path(tempfile.gettempdir()) if writes_in_place(path) else target.parent
    return folder / _hidden_name(target.name, "partial", pid)


def publish(temporary: Path, path: str | Path) -> None:
    """The whole file ``temporary`` (:func:`partial_path`) at ``path``: renamed onto the
    file ``path`` resolves to (a file replaced keeps its permissions), or, for an output
    written in place, copied into it and removed (:class:`OSError` if that fails;
    ``temporary`` is removed then too)."""
    if not writes_in_place(path):
        target = output_target(path)
        _keep_mode(temporary, target)
        os.replace(temporary, target)
        return
    try:
        with temporary.open("rb") as source, open(path, "wb") as stream:
            shutil.copyfileobj(source, stream, 1 << 20)
    finally:
        with contextlib.suppress(OSError):
            temporary.unlink(missing_ok=True)


def _keep_mode(temporary: Path, target: Path) -> None:
    """A file about to replace ``target`` takes its permissions, if it exists (a new one
    keeps what the umask gave it)."""
    try:
        mode = target.stat().st_mode & 0o7777
    except FileNotFoundError:
        return
    os.chmod(temporary, mode)


def write_atomically(path: str | Path, data: bytes | Iterable[bytes]) -> None:
    """Write a whole file or nothing: a run stopped half-way leaves the old file (or
    none), never a part (:func:`partial_path` until it is whole). ``data``: the bytes,
    or pieces of them made as they are written. A file replaced keeps its permissions;
    a new one gets what the umask gives any new file. Through a symbolic link, the file
    it points to is written (the link stays); a character device or a FIFO is written
    into, as a stream (:func:`writes_in_place`: no rename can make that atomic)."""
    pieces = [data] if isinstance(data, bytes) else data
    if writes_in_place(path):
        with open(path, "wb") as stream:
            stream.writelines(pieces)
        return
    target = output_target(path)
    temporary = partial_path(target)
    try:
        with temporary.open("wb") as stream:
            stream.writelines(pieces)
            stream.flush()
            os.fsync(stream.fileno())
        _keep_mode(temporary, target)
        os.replace(temporary, target)
    finally:
        with contextlib.suppress(OSError):  # (a read-only folder refuses even this)
            temporary.unlink(missing_ok=True)
