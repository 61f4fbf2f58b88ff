"""Autopilot onboard logs read in bulk: ArduPilot DataFlash (``.bin``) and PX4 ULog (``.ulg``).

:func:`load` picks the reader by the file's content (not its name) and returns an
:class:`~mavest.onboard.model.OnboardLog` in SI units, body FRD and NED; :func:`detect`
only says which format a file is. An unusable file raises :class:`OnboardLogError` with
a one-line message; a damaged but partly readable one loads, its damage counted in
``OnboardLog.damage``.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

from mavest.onboard.errors import OnboardLogError
from mavest.onboard.model import ImuStream, LogDamage, OnboardLog, Series

__all__ = [
    "ImuStream",
    "LogDamage",
    "OnboardLog",
    "OnboardLogError",
    "Series",
    "detect",
    "load",
]

# A DataFlash log opens with a FMT record (header A3 95, type 128) describing FMT itself;
# a ULog with its magic and a version byte after it.
_DATAFLASH_MAGIC = bytes([0xA3, 0x95, 0x80])
_ULOG_MAGIC = b"ULog\x01\x12\x35"
# That first record whole: FMT (128) of length 89 named "FMT". Found further in (after a
# logger's own header), it marks a DataFlash log as surely as at the start: nine bytes
# that noise, or another format's data, does not make.
_DATAFLASH_FMT_OF_FMT = _DATAFLASH_MAGIC + bytes([0x80, 89]) + b"FMT\x00"
# How far into a file the DataFlash start is looked for.
_DATAFLASH_SEARCH = 1 << 16


def detect(path: Path | str) -> str | None:
    """``"dataflash"``, ``"ulog"`` or None, from the file's first bytes.

    OnboardLogError if the file cannot be read at all (absent, a folder, no permission).
    """
    try:
        with Path(path).open("rb") as file:
            head = file.read(len(_ULOG_MAGIC))
    except OSError as error:
        raise OnboardLogError(f"{path}: cannot read ({error.strerror or error})") from error
    if head.startswith(_DATAFLASH_MAGIC):
        return "dataflash"
    if head.startswith(_ULOG_MAGIC):
        return "ulog"
    return None


def _dataflash_further_in(path: Path | str) -> bool:
    """Whether a DataFlash log's first record comes within the file's first
    :data:`_DATAFLASH_SEARCH` bytes, not at its start (a board's logger may write a
    header of its own first)."""
    with contextlib.suppress(OSError), Path(path).open("rb") as file:
        return _DATAFLASH_FMT_OF_FMT in file.read(_DATAFLASH_SEARCH)
    return False


def load(path: Path | str) -> OnboardLog:
    """Read an onboard log of either format, chosen by content (a DataFlash log also when
    it starts within the file's first 64 KiB, after bytes of another kind).

    OnboardLogError (one line) for a file that is neither format, or holds no IMU samples.
    """
    kind = detect(path)
    if kind is None and _dataflash_further_in(path):
        kind = "dataflash"  # (its reader skips what comes before, counted as damage)
    if kind == "dataflash":
        from mavest.onboard.dataflash import load_dataflash

        return load_dataflash(path)
    if kind == "ulog":
        from mavest.onboard.ulog import load_ulog

        return load_ulog(path)
    size = Path(path).stat().st_size
    what = "an empty file" if size == 0 else "neither an ArduPilot DataFlash log nor a PX4 ULog"
    raise OnboardLogError(f"{Path(path).name}: {what}")
