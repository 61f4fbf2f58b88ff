"""Telemetry logs (.tlog): each record an 8-byte big-endian Unix time in µs, then one packet.

The reader splits records by the packets' own length fields and resynchronises
past damage (garbage, a truncated packet, a bad CRC) by looking for the next
position where a plausible timestamp is followed by a MAVLink start byte, the
way pymavlink's robust reading does. Only the messages a caller asks for are
decoded (and CRC-checked); every other record passes through untouched, so an
output tlog can hold every input record.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from mavest.mavlink.messages import MAVLink, mavlink2

_STX_V1 = 0xFE
_STX_V2 = 0xFD
_TIMESTAMP = struct.Struct(">Q")
_MAX_TIMESTAMP_JUMP_US = 3 * 24 * 3600 * 10**6  # as pymavlink: beyond this a "timestamp" is noise


class TlogError(Exception):
    """A file that is not a usable tlog (the message says why, in one line)."""


def message_id_of(packet: bytes | memoryview) -> int:
    """The message id in a MAVLink 1 or 2 packet's header."""
    if packet[0] == _STX_V2:
        return packet[7] | (packet[8] << 8) | (packet[9] << 16)
    return packet[5]


def message_ids(names: tuple[str, ...] | list[str] | set[str]) -> frozenset[int]:
    return frozenset(getattr(mavlink2, f"MAVLINK_MSG_ID_{name}") for name in names)


def _packet_length(buffer: bytes | memoryview, start: int) -> int:
    """Length of the packet at ``start`` from its header, or 0 if no packet starts there."""
    stx = buffer[start]
    if stx == _STX_V2:
        if start + 3 > len(buffer):
            return -1
        signed = buffer[start + 2] & 0x01
        return 12 + buffer[start + 1] + (13 if signed else 0)
    if stx == _STX_V1:
        if start + 2 > len(buffer):
            return -1
        return 8 + buffer[start + 1]
    return 0


@dataclass
class TlogStats:
    """What reading a tlog found: records and damage."""

    records: int = 0
    bad_crc: int = 0  # a decode was attempted and the packet was damaged
    skipped_bytes: int = 0  # garbage between records, resynchronised past
    truncated_bytes: int = 0  # a record cut off at the end of the file


@dataclass(frozen=True)
class TlogRecord:
    timestamp_us: int
    packet: bytes
    message: Any | None  # the decoded message if its id was wanted and it decoded


class TlogReader:
    """Records of a tlog, decoding only the wanted message ids.

    >>> reader = TlogReader(path, wanted=message_ids(["RAW_IMU"]))  # doctest: +SKIP
    >>> for record in reader: ...  # doctest: +SKIP
    """

    def __init__(self, data: bytes, wanted: frozenset[int] | None = None) -> None:
        self._data = data
        self._wanted = wanted
        self._mav = MAVLink(None)
        self._mav.robust_parsing = False
        self.stats = TlogStats()
        self.position = 0

    @classmethod
    def open(cls, path: str | Path, wanted: frozenset[int] | None = None) -> TlogReader:
        """Read a whole file; a missing path, a directory or a non-tlog is a :class:`TlogError`."""
        path = Path(path)
        if path.is_dir():
            raise TlogError(f"{path} is a directory, not a tlog")
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise TlogError(f"{path}: no such file") from None
        except OSError as error:
            raise TlogError(f"cannot read {path}: {error.strerror}") from None
        if not data:
            raise TlogError(f"{path} is empty")
        reader = cls(data, wanted)
        if not reader.looks_like_tlog():
            raise TlogError(
                f"{path} is not a MAVLink telemetry log (.tlog): no timestamped MAVLink "
                "packet in its first kilobytes"
            )
        return reader

    @property
    def size(self) -> int:
        return len(self._data)

    def looks_like_tlog(self, probe: int = 4096) -> bool:
        """True when a timestamped packet with a valid CRC starts within the first bytes."""
        data = self._data[: probe + 300]
        for start in range(min(probe, max(0, len(data) - 9))):
            if data[start + 8] not in (_STX_V1, _STX_V2):
                continue
            length = _packet_length(data, start + 8)
            end = start + 8 + length
            if length <= 0 or end > len(data):
                continue
            try:
                self._mav.decode(bytearray(data[start + 8 : end]))
            except Exception:
                continue
            return True
        return False

    def _resynchronise(self, start: int, last_us: int | None) -> int:
        """The next position after ``start`` where a plausible record begins."""
        data = self._data
        n = len(data)
        position = start + 1
        while position + 9 <= n:
            found = data.find(bytes([_STX_V2]), position + 8)
            found_v1 = data.find(bytes([_STX_V1]), position + 8)
            candidates = [c for c in (found, found_v1) if c >= 0]
            if not candidates:
                return n
            position = min(candidates) - 8
            (stamp,) = _TIMESTAMP.unpack_from(data, position)
            if last_us is None or abs(stamp - last_us) <= _MAX_TIMESTAMP_JUMP_US:
                return position
            position += 1
        return n

    def __iter__(self) -> Iterator[TlogRecord]:
        data = self._data
        n = len(data)
        wanted = self._wanted
        decode = self._mav.decode
        position = self.position
        last_us: int | None = None
        stats = self.stats
        while position + 9 <= n:
            length = _packet_length(data, position + 8)
            (stamp,) = _TIMESTAMP.unpack_from(data, position)
            plausible = last_us is None or abs(stamp - last_us) <= _MAX_TIMESTAMP_JUMP_US
            if length <= 0 or not plausible:
                resumed = self._resynchronise(position, last_us)
                stats.skipped_bytes += resumed - position
                position = resumed
                continue
            end = position + 8 + length
            if end > n:
                stats.truncated_bytes += n - position
                position = n
                break
            packet = data[position + 8 : end]
            message = None
            if wanted is None or message_id_of(packet) in wanted:
                try:
                    message = decode(bytearray(packet))
                except Exception:  # pymavlink's MAVError, or struct's on a short payload
                    # a damaged packet may hide the start of the next record: resync
                    stats.bad_crc += 1
                    resumed = self._resynchronise(position, last_us)
                    stats.skipped_bytes += resumed - position
                    position = resumed
                    continue
            stats.records += 1
            last_us = stamp
            position = end
            self.position = position
            yield TlogRecord(stamp, packet, message)
        self.position = position


class TlogWriter:
    """Appends records to a tlog; every record is complete on disk after :meth:`flush`."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self._file: IO[bytes] = self.path.open("wb")
        except OSError as error:
            raise TlogError(f"cannot write {self.path}: {error.strerror}") from None
        self.records = 0

    def write(self, timestamp_us: int, packet: bytes) -> None:
        self._file.write(_TIMESTAMP.pack(timestamp_us) + packet)
        self.records += 1

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()

    def __enter__(self) -> TlogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
