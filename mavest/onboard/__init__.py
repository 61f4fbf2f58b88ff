"""Autopilot onboard logs read in bulk: ArduPilot DataFlash (``.bin``) and PX4 ULog (``.ulg``).

:func:`load` picks the reader by the file's content (not its name) and returns an
:class:`~mavest.onboard.model.OnboardLog` in SI units, body FRD and NED; :func:`detect`
only says which format a file is. An unusable file raises :class:`OnboardLogError` with
a one-line message; a damaged but partly readable one loads, its damage counted in
``OnboardLog.damage``.
"""

from __future__ import annotations

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


def load(path: Path | str) -> OnboardLog:
    """Read an onboard log of either format, chosen by content.

    OnboardLogError (one line) for a file that is neither format, or holds no IMU samples.
    """
    kind = detect(path)
    if kind == "dataflash":
        from mavest.onboard.dataflash import load_dataflash

        return load_dataflash(path)
    if kind == "ulog":
        from mavest.onboard.ulog import load_ulog

        return load_ulog(path)
    size = Path(path).stat().st_size
    what = "an empty file" if size == 0 else "neither an ArduPilot DataFlash log nor a PX4 ULog"
    raise OnboardLogError(f"{Path(path).name}: {what}")
