"""Telemetry logs (.tlog): each record an 8-byte big-endian Unix time in µs, then one packet.

The reader splits records by the packets' own length fields and resynchronises
past damage (garbage, a truncated packet, a bad CRC) by looking for the next
position where a plausible timestamp is followed by a MAVLink start byte, the
way pymavlink's robust reading does. Only the messages a caller asks for are
decoded (and CRC-checked); every other record passes through untouched, so an
output tlog can hold every input record.

A timestamp is plausible within days of the last record's. One further off is
believed, as :mod:`mavest.timeline` believes a far-off time, when the records from
it on continue it (a ground station's clock set anew, say by NTP, 1970 to today):
a lone absurd timestamp, which the next records contradict, is damage.
"""

from __future__ import annotations

import bisect
import contextlib
import logging
import mmap
import os
import stat
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import IO, Any

import numpy as np

from mavest import timeline
from mavest.mavlink import framing
from mavest.mavlink.messages import MAVLink, mavlink2

_TIMESTAMP = struct.Struct(">Q")
_MAX_TIMESTAMP_JUMP_US = 3 * 24 * 3600 * 10**6  # as pymavlink: beyond this, confirm a time
# Where a tlog's first record is looked for. In the first bytes one timestamped packet
# will do; further on, as the bytes searched grow, so does the chance that noise holds
# a packet whose CRC happens to match, so a run of records is asked for, and only so
# far: a file that is not a tlog is refused after this much.
_PROBE_BYTES = 4096
_SEARCH_BYTES = 1 << 20


class TlogError(Exception):
    """A file that is not a usable tlog (the message says why, in one line)."""


def message_id_of(packet: bytes | memoryview) -> int:
    """The message id in a MAVLink 1 or 2 packet's header."""
    if packet[0] == framing.STX_V2:
        return packet[7] | (packet[8] << 8) | (packet[9] << 16)
    return packet[5]


def message_ids(names: tuple[str, ...] | list[str] | set[str]) -> frozenset[int]:
    return frozenset(getattr(mavlink2, f"MAVLINK_MSG_ID_{name}") for name in names)


def _packet_length(buffer: bytes | memoryview | mmap.mmap, start: int) -> int:
    """Length of the packet at ``start`` from its header, or 0 if no packet starts there."""
    stx = buffer[start]
    if stx == framing.STX_V2:
        if start + 3 > len(buffer):
            return -1
        signed = buffer[start + 2] & 0x01
        return 12 + buffer[start + 1] + (13 if signed else 0)
    if stx == framing.STX_V1:
        if start + 2 > len(buffer):
            return -1
        return 8 + buffer[start + 1]
    return 0


def _record_starts(data: bytes | mmap.mmap, position: int, last_us: int) -> bool:
    """True at the end of the data, or where a record plausibly starts: a timestamp near
    the previous one, then a MAVLink start byte."""
    if position == len(data):
        return True
    if position + 9 > len(data) or data[position + 8] not in (framing.STX_V1, framing.STX_V2):
        return False
    (stamp,) = _TIMESTAMP.unpack_from(data, position)
    return abs(stamp - last_us) <= _MAX_TIMESTAMP_JUMP_US


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

    def __init__(
        self,
        data: bytes | mmap.mmap,
        wanted: frozenset[int] | None = None,
        name: str = "tlog",
        boot_epoch_us: int | None = None,
    ) -> None:
        self._data = data
        self.name = name  # for the log's lines about it
        # records stamped with a log's boot time from this Unix time (an onboard log's,
        # converted in memory): its lines speak of that clock, not of bytes or dates
        self._boot_epoch_us = boot_epoch_us
        self._wanted = wanted
        self._mav = MAVLink(None)
        self._mav.robust_parsing = False
        self.stats = TlogStats()
        self.position = 0
        self._last_us: int | None = None  # the last record's time
        self._released = 0  # the mapped file's pages before this are given back
        self._array: np.ndarray | None = None  # the file as bytes for compiled code

    @classmethod
    def open(cls, path: str | Path, wanted: frozenset[int] | None = None) -> TlogReader:
        """Open a file; a missing path, a directory, anything but a regular file (a
        pipe, a device) or a non-tlog is a :class:`TlogError`.

        The file is mapped, not read: memory stays flat however long the log (pages
        behind the reader are released as it goes), and opening is instant. A pipe or
        a device has no end to map (/dev/zero would be read until memory runs out, a
        serial port until unplugged): it is refused before it is opened, which for a
        serial port could reset the board behind it.
        """
        path = Path(path)
        try:
            _check_regular(path, path.stat().st_mode)
            # not blocking: a pipe put in the file's place since would wait for a writer
            with open(path, "rb", opener=_open_nonblocking) as file:
                status = os.fstat(file.fileno())
                _check_regular(path, status.st_mode)
                data: bytes | mmap.mmap = b""
                if status.st_size:
                    try:
                        data = mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ)
                    except (ValueError, OSError):  # a file system that cannot map: read it
                        data = file.read()
        except FileNotFoundError:
            raise TlogError(f"{path}: no such file") from None
        except OSError as error:
            raise TlogError(f"cannot read {path}: {error.strerror}") from None
        if not data:
            raise TlogError(f"{path} is empty")
        reader = cls(data, wanted, name=path.name)
        start = reader.first_record()
        if start is None:
            raise TlogError(
                f"{path} is not a MAVLink telemetry log (.tlog): no timestamped MAVLink "
                f"packets in its first {_SEARCH_BYTES >> 20} MiB"
            )
        # what comes before the first record is damage, skipped (a junk record that
        # happened to look whole must not be read as the log's first)
        reader.position = reader.stats.skipped_bytes = start
        return reader

    @property
    def size(self) -> int:
        return len(self._data)

    def first_record(self) -> int | None:
        """Where the first record starts, or None when the data does not look like a tlog.

        In the first bytes (``_PROBE_BYTES``) a timestamped packet with a valid CRC will
        do, unless a packet follows it at once: that is MAVLink without timestamps (a raw
        capture), whose packets' tails would be read as timestamps. In a tlog the next
        record starts with a timestamp, whose first byte stays 0 until the year 2540,
        never a start byte. Further on (garbage before the log), up to
        ``_SEARCH_BYTES``, the first record of a run that continues its time
        (:meth:`_timeline_starts`; never in a raw capture, for the same reason).
        """
        data = self._data[: _PROBE_BYTES + 600]  # room for two whole packets after the probe
        for start in range(min(_PROBE_BYTES, max(0, len(data) - 9))):
            if not self._packet_at(data, start + 8):
                continue
            end = start + 8 + _packet_length(data, start + 8)
            if end < len(data) and self._packet_at(data, end):
                continue
            return start
        array = self.array
        stop = min(len(array) - 9, _SEARCH_BYTES)
        if stop <= _PROBE_BYTES:
            return None
        window = array[_PROBE_BYTES : stop + 8]
        starts = (window[8:] == framing.STX_V1) | (window[8:] == framing.STX_V2)
        starts &= window[:-8] < 0x80  # a time in 63 bits, as framing.scan reads one
        for offset in np.flatnonzero(starts):
            if self._timeline_starts(_PROBE_BYTES + int(offset)):
                return _PROBE_BYTES + int(offset)
        return None

    def _timeline_starts(self, position: int) -> bool:
        """Whether records on a time of their own start at ``position``: as
        :mod:`mavest.timeline` confirms a far-off time, ``timeline.CONFIRM`` whole
        records in a row (CRC valid, of known messages: :func:`framing.scan`), each
        continuing the one before (not :func:`timeline.far_off` it; tlog records may
        share a time). A clock that jumped and stays passes; a lone absurd timestamp,
        the records after it on the old time, does not."""
        records = framing.scan(self.array, position, -1, timeline.CONFIRM)
        if len(records) < timeline.CONFIRM:
            return False
        return not any(
            timeline.far_off(step * 1e-6, timeline.REORDER_WINDOW, timeline.MAX_STEP)
            for step in np.diff(records.stamp).tolist()
        )

    def _packet_at(self, data: bytes, start: int) -> bool:
        """True when a whole packet of a known message, CRC valid, starts at ``start``
        (an id the dialect does not know has no CRC to check: noise passes it)."""
        if start >= len(data) or data[start] not in (framing.STX_V1, framing.STX_V2):
            return False
        length = _packet_length(data, start)
        if length <= 0 or start + length > len(data):
            return False
        try:
            message = self._mav.decode(bytearray(data[start : start + length]))
        except Exception:
            return False
        return not isinstance(message, mavlink2.MAVLink_unknown)

    def _resynchronise(self, start: int, last_us: int | None) -> int:
        """The next position after ``start`` where a plausible record begins."""
        data = self._data
        n = len(data)
        position = start + 1
        while position + 9 <= n:
            found = data.find(bytes([framing.STX_V2]), position + 8)
            found_v1 = data.find(bytes([framing.STX_V1]), position + 8)
            candidates = [c for c in (found, found_v1) if c >= 0]
            if not candidates:
                return n
            position = min(candidates) - 8
            (stamp,) = _TIMESTAMP.unpack_from(data, position)
            if (
                last_us is None
                or abs(stamp - last_us) <= _MAX_TIMESTAMP_JUMP_US
                or self._timeline_starts(position)
            ):
                return position
            position += 1
        return n

    @property
    def array(self) -> np.ndarray:
        """The file as a read-only uint8 array (no copy: the mapping's pages)."""
        if self._array is None:
            self._array = np.frombuffer(self._data, dtype=np.uint8)
        return self._array

    def scan(self, capacity: int) -> framing.RecordIndex:
        """The next clean records (at most ``capacity``), indexed and passed over.

        Clean: a plausible timestamp, a whole packet of a message this dialect
        defines, its CRC valid (:func:`mavest.mavlink.framing.scan`). Stops at the
        first record that is not; iterating the reader from there reads it (and
        whatever damage follows) the careful way. Empty when no clean record is next.
        """
        last_us = -1 if self._last_us is None else self._last_us
        records = framing.scan(self.array, self.position, last_us, capacity)
        if len(records):
            self.position = int(records.end[-1])
            self._last_us = int(records.stamp[-1])
            self.stats.records += len(records)
            self._release_behind()
        return records

    def _release_behind(self) -> None:
        data = self._data
        if self.position - self._released > _RELEASE_BYTES and isinstance(data, mmap.mmap):
            self._released = _release_pages(data, self.position - _RELEASE_BYTES // 2)

    def __iter__(self) -> Iterator[TlogRecord]:
        """Records from the current position on (the reader's position and last time
        follow each record given out, so :meth:`scan` can take over between them)."""
        data = self._data
        n = len(data)
        wanted = self._wanted
        decode = self._mav.decode
        position = self.position
        stats = self.stats
        while position + 9 <= n:
            last_us = self._last_us
            self._release_behind()
            length = _packet_length(data, position + 8)
            (stamp,) = _TIMESTAMP.unpack_from(data, position)
            plausible = last_us is None or abs(stamp - last_us) <= _MAX_TIMESTAMP_JUMP_US
            if length > 0 and not plausible:  # the clock set anew, or one absurd time
                plausible = self._timeline_starts(position)
            if length <= 0 or not plausible:
                resumed = self._resynchronise(position, last_us)
                stats.skipped_bytes += resumed - position
                position = self.position = resumed
                continue
            end = position + 8 + length
            if end > n:
                # the last record cut off, or junk that looks like a record start
                resumed = self._resynchronise(position, last_us)
                if resumed >= n:
                    stats.truncated_bytes += n - position
                    position = self.position = n
                    break
                stats.skipped_bytes += resumed - position
                position = self.position = resumed
                continue
            packet = data[position + 8 : end]
            message = None
            is_wanted = wanted is None or message_id_of(packet) in wanted
            # An unwanted packet is checked too when no record follows it: junk that looks
            # like a record start would otherwise swallow the real records its length spans.
            if is_wanted or not _record_starts(data, end, stamp):
                try:
                    decoded = decode(bytearray(packet))
                except Exception:  # pymavlink's MAVError, or struct's on a short payload
                    # a damaged packet may hide the start of the next record: resync
                    stats.bad_crc += 1
                    resumed = self._resynchronise(position, last_us)
                    stats.skipped_bytes += resumed - position
                    position = self.position = resumed
                    continue
                if isinstance(decoded, mavlink2.MAVLink_unknown) and not is_wanted:
                    # an id this dialect does not know has no CRC to check, and nothing
                    # after it lines up: take it for junk
                    stats.bad_crc += 1
                    resumed = self._resynchronise(position, last_us)
                    stats.skipped_bytes += resumed - position
                    position = self.position = resumed
                    continue
                if is_wanted:
                    message = decoded
            stats.records += 1
            if last_us is not None and abs(stamp - last_us) > _MAX_TIMESTAMP_JUMP_US:
                _log.warning(
                    "%s", _clock_jump(self.name, last_us, stamp, position, self._boot_epoch_us)
                )
            self._last_us = stamp
            position = self.position = end
            yield TlogRecord(stamp, packet, message)
        self.position = position


def _clock_jump(
    name: str, before_us: int, after_us: int, position: int, boot_epoch_us: int | None = None
) -> str:
    """The line saying that a tlog's recording clock jumped (to a time that stays); with
    ``boot_epoch_us``, that a log's own clock did, at which of its times."""
    way = "forward" if after_us > before_us else "back"
    span = _span(abs(after_us - before_us))
    if boot_epoch_us is not None:
        where = f"at {(before_us - boot_epoch_us) * 1e-6:.3f} s of its time"
        return f"{name}: the log's clock jumped {way} by {span} {where}; read on at the new time"
    return (
        f"{name}: the recording clock jumped {way} by {span} at byte {position} "
        f"({_utc(before_us)} → {_utc(after_us)}); the records after it are read at the new time"
    )


def _span(us: int) -> str:
    days = us / (86_400 * 10**6)
    return f"{days:.1f} days" if days < 365.25 else f"{days / 365.25:.1f} years"


def _utc(us: int) -> str:
    try:
        return datetime.fromtimestamp(us * 1e-6, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    except (OverflowError, ValueError, OSError):  # beyond the year 9999
        return f"{us} µs"


def _check_regular(path: Path, mode: int) -> None:
    """A :class:`TlogError` unless ``mode`` is a regular file's."""
    if stat.S_ISDIR(mode):
        raise TlogError(f"{path} is a directory, not a tlog")
    if not stat.S_ISREG(mode):
        kind = (
            "a pipe (FIFO)"
            if stat.S_ISFIFO(mode)
            else "a device"
            if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
            else "a socket"
            if stat.S_ISSOCK(mode)
            else "not a file"
        )
        raise TlogError(f"{path} is {kind}: a tlog is read from a regular file, which ends")


def _open_nonblocking(path: str, flags: int) -> int:
    return os.open(path, flags | getattr(os, "O_NONBLOCK", 0))


# A mapped tlog's pages behind the reader are released in steps of this many bytes
# (they are the file's: read again from it, should a resynchronisation look back).
_RELEASE_BYTES = 32 << 20


def _release_pages(data: mmap.mmap, end: int) -> int:
    """Give back the mapping's pages before ``end``; the page boundary released to."""
    boundary = end - end % mmap.PAGESIZE
    if boundary > 0 and hasattr(mmap, "MADV_DONTNEED"):
        data.madvise(mmap.MADV_DONTNEED, 0, boundary)
    return boundary


_log = logging.getLogger("mavest")


class TlogWriter:
    """Appends records to a tlog; every record is complete on disk after :meth:`flush`.

    Records reach the file only whole (buffered here, written in one piece), so the
    file always ends at a record boundary: a process killed between writes leaves a
    valid tlog. A write that fails (disk full, quota, I/O error) is reported once in
    the log, the file is cut back to its last whole record and the writer stops
    writing; the caller goes on (:attr:`error` says what happened).
    """

    BUFFER_BYTES = 64 * 1024  # pending records are written once this much accumulates

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            # unbuffered: the buffering is ours, so that we know what reached the file
            self._file: IO[bytes] = self.path.open("wb", buffering=0)
        except OSError as error:
            raise TlogError(f"cannot write {self.path}: {error.strerror}") from None
        self.records = 0  # records written or pending (after a failure: those on disk)
        self.error: str | None = None  # why writing stopped, if it did
        self._pending = bytearray()
        self._pending_ends: list[int] = []  # where each pending record ends in _pending
        self._on_disk = 0  # bytes of whole records in the file

    def write(self, timestamp_us: int, packet: bytes) -> None:
        if self.error is not None:
            return
        self._pending += _TIMESTAMP.pack(timestamp_us)
        self._pending += packet
        self._pending_ends.append(len(self._pending))
        self.records += 1
        if len(self._pending) >= self.BUFFER_BYTES:
            self._write_pending()

    def write_records(self, data: np.ndarray, ends: np.ndarray) -> None:
        """Whole records at once: ``data`` their bytes (uint8), ``ends`` where each ends
        in it. As many as fill the buffer go to the file straight from ``data``."""
        if self.error is not None or not ends.shape[0]:
            return
        if len(self._pending) + data.shape[0] < self.BUFFER_BYTES:
            base = len(self._pending)
            self._pending += data.tobytes()
            self._pending_ends.extend((ends + base).tolist())
            self.records += int(ends.shape[0])
            return
        if self._pending:
            self._write_pending()
            if self.error is not None:
                return
        self.records += int(ends.shape[0])
        with memoryview(np.ascontiguousarray(data)) as view:
            self._write_out(view, ends)

    def _write_pending(self) -> None:
        with memoryview(self._pending) as data:
            self._write_out(data, self._pending_ends)
        if self.error is None:
            self._pending.clear()
            self._pending_ends.clear()

    def _write_out(self, data: memoryview, ends: Sequence[int] | np.ndarray) -> None:
        """Whole records to the file (``ends``: where each ends in ``data``)."""
        done = 0
        try:
            while done < len(data):
                done += self._file.write(data[done:]) or 0
        except OSError as error:
            self._stop(error, done, ends)
            return
        self._on_disk += done

    def _stop(self, error: OSError, done: int, ends: Sequence[int] | np.ndarray) -> None:
        """Cut the file back to its last whole record (of those being written, which
        end at ``ends``; ``done`` bytes of them reached the file) and write no more."""
        whole = bisect.bisect_right(ends, done)
        self.records -= len(ends) - whole
        keep = self._on_disk + (int(ends[whole - 1]) if whole else 0)
        with contextlib.suppress(OSError):  # a device (/dev/full) cannot be truncated
            self._file.truncate(keep)
        with contextlib.suppress(OSError):
            self._file.close()
        self._pending = bytearray()
        self._pending_ends = []
        self.error = f"cannot write {self.path}: {error.strerror or error}"
        _log.error(
            "%s; the tlog stops here with its first %d records, whole (estimating on)",
            self.error,
            self.records,
        )

    def flush(self) -> None:
        if self.error is None and self._pending:
            self._write_pending()

    def close(self) -> None:
        if self._file.closed:
            return
        self.flush()
        if not self._file.closed:
            self._file.close()

    def __enter__(self) -> TlogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
