"""MAVLink packets found, checked and made in compiled loops: mavest's one packet
scanner, its one CRC and its one packer.

Every path on which mavest reads or writes MAVLink bytes itself goes through here:

* :func:`scan` indexes the records of a clean stretch of a tlog (timestamp, start
  byte, length, known message id, valid CRC) and stops at the first record that is
  anything else, which the careful :class:`~mavest.mavlink.tlog.TlogReader` then
  hands to pymavlink's parser. A clean log goes through here whole; damage costs
  only itself.
* :func:`scan_packets` does the same for bare packets, as a UDP datagram holds them:
  :func:`mavest.mavlink.wire.decode_datagram` builds message objects from its index.
* :func:`find_packets` finds the clean packets among damage (noise, false starts,
  bad CRCs, ids the dialect does not know) in what the live links hear, stepping
  past each bad start to the next start byte.
* :func:`pack_rows` packs messages, one or many at a time, as pymavlink packs them
  (MAVLink 2 with the payload's trailing zeros cut, or MAVLink 1, the base fields
  whole), each with its own sequence number: mavest's own messages on the live
  path (:func:`mavest.mavlink.wire.pack`) and the replay's answers in bulk.

The CRC is MAVLink's X.25 (CRC-16/MCRF4XX) over the packet after its start byte and
the message's extra byte (:data:`CRC_EXTRA`). It runs inside the compiled loops,
where no library's CRC can be called; tests/test_framing.py checks it, the scanner
and the packer against pymavlink on the same bytes.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavest._jit import inplace_exact_kernel, inplace_inlined_kernel

_MAX_TIMESTAMP_JUMP_US = 3 * 24 * 3600 * 10**6  # as TlogReader (and pymavlink)
_SMALLEST_PACKET = 8  # bytes: MAVLink 1's header and CRC around an empty payload
# MAVLink 2's and MAVLink 1's start bytes
STX_V2, STX_V1 = mavlink2.PROTOCOL_MARKER_V2, mavlink2.PROTOCOL_MARKER_V1

# CRC extra byte per message id; -1 for ids this dialect does not define.
CRC_EXTRA = np.full(max(mavlink2.mavlink_map) + 1, -1, dtype=np.int16)
for _id, _class in mavlink2.mavlink_map.items():
    CRC_EXTRA[_id] = _class.crc_extra


@functools.cache
def mavlink1_lengths() -> dict[int, int]:
    """The MAVLink 1 payload length of each message MAVLink 1 can carry: its fields
    without the extensions, which MAVLink 1 does not have (the MAVLink 1 dialect's whole
    payload). Its dialect is loaded on first use, as few vehicles need it."""
    from pymavlink.dialects.v10 import ardupilotmega as mavlink1

    return {
        message_id: message_class.unpacker.size
        for message_id, message_class in mavlink1.mavlink_map.items()
    }


class RecordIndex(NamedTuple):
    """Where each record of a clean stretch is, and what it carries (arrays of one length)."""

    start: np.ndarray  # int64: the record's first byte (its timestamp) in the file
    end: np.ndarray  # int64: one past its packet's last byte
    payload: np.ndarray  # int64: its payload's first byte
    payload_length: np.ndarray  # int64
    message_id: np.ndarray  # int64
    system: np.ndarray  # int64
    component: np.ndarray  # int64
    stamp: np.ndarray  # int64: the record's time, µs

    def __len__(self) -> int:
        return int(self.start.shape[0])

    def part(self, selection: Any) -> RecordIndex:
        return RecordIndex(*(column[selection] for column in self))


def _x25_tables(count: int) -> np.ndarray:
    """Tables for MAVLink's CRC (X.25, CRC-16/MCRF4XX: reflected polynomial 0x8408)
    eight bytes at a time: row k, entry b is the CRC register after byte b followed
    by k zero bytes, from a zero register. The CRC is linear in the register and the
    bytes, so eight bytes b0…b7 take the register c to
    T7[(c & 0xFF) ^ b0] ^ T6[(c >> 8) ^ b1] ^ T5[b2] ^ … ^ T0[b7]: eight lookups
    independent of each other instead of eight steps each waiting for the last
    (slicing-by-8; the replay's scan and packing were a fifth of its processing)."""
    tables = np.empty((count, 256), dtype=np.int64)
    register = np.arange(256, dtype=np.int64)
    for _ in range(8):
        register = np.where(register & 1, (register >> 1) ^ 0x8408, register >> 1)
    tables[0] = register
    for k in range(1, count):
        previous = tables[k - 1]
        tables[k] = (previous >> 8) ^ tables[0][previous & 0xFF]
    return tables


# (unsigned, as the CRC's arithmetic is: a signed index may count from the end, and
# the test for that slows every lookup, by a third over a packet's CRC)
_X25 = _x25_tables(8).astype(np.uint64)
_U8 = np.uint64(8)
_LOW_BYTE = np.uint64(0xFF)


@inplace_exact_kernel
def _x25_update(crc: int, byte: int) -> int:
    register = np.uint64(crc)
    index = (register ^ np.uint64(byte)) & _LOW_BYTE
    return np.int64((register >> _U8) ^ _X25[0, index])


@inplace_exact_kernel
def crc_register(data: np.ndarray, start: int, stop: int, crc: int) -> int:
    """The CRC register after bytes [start, stop) of ``data``, from ``crc`` (0xFFFF
    to begin a packet's)."""
    k = np.uint64(start)
    end = np.uint64(stop)
    register = np.uint64(crc)
    while k + _U8 <= end:
        register = (
            _X25[7, (register & _LOW_BYTE) ^ data[k]]
            ^ _X25[6, (register >> _U8) ^ data[k + np.uint64(1)]]
            ^ _X25[5, data[k + np.uint64(2)]]
            ^ _X25[4, data[k + np.uint64(3)]]
            ^ _X25[3, data[k + np.uint64(4)]]
            ^ _X25[2, data[k + np.uint64(5)]]
            ^ _X25[1, data[k + np.uint64(6)]]
            ^ _X25[0, data[k + np.uint64(7)]]
        )
        k += _U8
    while k < end:
        register = (register >> _U8) ^ _X25[0, (register & _LOW_BYTE) ^ data[k]]
        k += np.uint64(1)
    return np.int64(register)


@inplace_inlined_kernel
def _header_at(data: np.ndarray, p: int) -> tuple[int, int, int, int, int, int]:
    """The header of the packet starting at ``p`` (``p`` < len(data)): its length, the
    payload's, the signature's, the message id, system and component. Its length is 0
    when no start byte is at ``p``, −1 when the header runs past the end of ``data``."""
    n = data.shape[0]
    stx = data[p]
    if stx == STX_V2:
        if p + 10 > n:
            return -1, 0, 0, 0, 0, 0
        message_id = (
            np.int64(data[p + 7]) | (np.int64(data[p + 8]) << 8) | (np.int64(data[p + 9]) << 16)
        )
        signature = 13 if data[p + 2] & 1 else 0
        system, component = np.int64(data[p + 5]), np.int64(data[p + 6])
        return 10, np.int64(data[p + 1]), signature, message_id, system, component
    if stx == STX_V1:
        if p + 6 > n:
            return -1, 0, 0, 0, 0, 0
        system, component = np.int64(data[p + 3]), np.int64(data[p + 4])
        return 6, np.int64(data[p + 1]), 0, np.int64(data[p + 5]), system, component
    return 0, 0, 0, 0, 0, 0


@inplace_exact_kernel
def _scan(
    data: np.ndarray,
    position: int,
    last_us: int,
    stamped: bool,
    crc_extra: np.ndarray,
    out: np.ndarray,
) -> tuple[int, int, int]:
    """Index clean records (``stamped``: each packet after its 8-byte big-endian time, as
    a tlog's) or bare packets from ``position`` into ``out`` (rows: the RecordIndex
    columns; stamp 0 for bare packets).

    Stops at the first record that is not clean or at ``out``'s capacity; returns
    (records, the position after the last, its timestamp). ``last_us`` < 0: none yet.
    """
    n = data.shape[0]
    count = 0
    capacity = out.shape[1]
    prefix = 8 if stamped else 0
    while count < capacity and position + prefix + 1 <= n:
        stamp = 0
        if stamped:
            for k in range(8):
                stamp = (stamp << 8) | np.int64(data[position + k])
            if stamp < 0:  # beyond int64: not a time
                break
            if last_us >= 0 and abs(stamp - last_us) > _MAX_TIMESTAMP_JUMP_US:
                break
        p = position + prefix
        header, length, signature, message_id, system, component = _header_at(data, p)
        if header <= 0:
            break
        end = p + header + length + 2 + signature
        if end > n or message_id >= crc_extra.shape[0] or crc_extra[message_id] < 0:
            break
        crc = crc_register(data, p + 1, p + header + length, 0xFFFF)
        crc = _x25_update(crc, crc_extra[message_id])
        body = p + header + length
        if crc != (np.int64(data[body]) | (np.int64(data[body + 1]) << 8)):
            break
        out[0, count] = position
        out[1, count] = end
        out[2, count] = p + header
        out[3, count] = length
        out[4, count] = message_id
        out[5, count] = system
        out[6, count] = component
        out[7, count] = stamp
        count += 1
        position = end
        if stamped:
            last_us = stamp
    return count, position, last_us


def scan(data: np.ndarray, position: int, last_us: int, capacity: int) -> RecordIndex:
    """The clean tlog records from ``position`` on, at most ``capacity`` (see :func:`_scan`)."""
    out = np.empty((8, capacity), dtype=np.int64)
    count, _, _ = _scan(data, position, last_us, True, CRC_EXTRA, out)
    return RecordIndex(*(np.ascontiguousarray(out[k, :count]) for k in range(8)))


def scan_packets(data: np.ndarray) -> tuple[np.ndarray, int]:
    """The clean bare packets at the front of ``data`` (uint8): their index as rows of the
    RecordIndex columns, shape (8, packets), and the position after the last (``data``'s
    length when every byte is in a clean packet)."""
    out = np.empty((8, data.shape[0] // _SMALLEST_PACKET + 1), dtype=np.int64)
    count, end, _ = _scan(data, 0, -1, False, CRC_EXTRA, out)
    return out[:, :count], end


class Found(NamedTuple):
    """What :func:`find_packets` found in bytes that may hold damage."""

    index: np.ndarray  # the clean packets, as rows of the RecordIndex columns: (8, packets)
    damaged: int  # stretches of bytes that were no clean packet, each skipped whole
    skipped: int  # the bytes in them
    end: int  # one past the last byte judged: the rest is a packet's start, cut off
    # whether the last stretch of damage runs to the end (a byte stream's may go on)
    ends_damaged: bool


def find_packets(data: np.ndarray, whole: bool, after_damage: bool = False) -> Found:
    """The clean packets (whole, a known message, CRC valid: :func:`_scan`'s test) in
    ``data`` (uint8), resynchronising past anything else at the next start byte after
    the one that failed, so that a false start (noise holding a start byte) costs only
    itself, not the packets its made-up length would span.

    ``whole``: nothing follows ``data`` (a datagram: a packet cut off at its end is
    damage). Otherwise (a byte stream: TCP, serial) a packet's start cut off at the end
    is left for the bytes to come: ``end`` says where it begins; and ``after_damage``
    says that the bytes before ended in damage, which noise at the front goes on (one
    stretch, counted once). An id this dialect does not know has no CRC to check it
    by, so it is judged damage as soon as its header is in, without waiting for the
    length it claims.
    """
    n = data.shape[0]
    parts: list[np.ndarray] = []
    damaged = skipped = 0
    position = 0
    ends_damaged = False
    starts: np.ndarray | None = None  # where start bytes are, looked up on the first damage
    while True:
        out = np.empty((8, (n - position) // _SMALLEST_PACKET + 1), dtype=np.int64)
        count, position, _ = _scan(data, position, -1, False, CRC_EXTRA, out)
        if count:
            parts.append(out[:, :count])
            ends_damaged = False
        if position >= n or (not whole and _cut_off(data, position)):
            break
        if starts is None:
            starts = np.flatnonzero((data == STX_V2) | (data == STX_V1))
        following = starts[np.searchsorted(starts, position, side="right") :]
        resumed = int(following[0]) if following.shape[0] else n
        if not (after_damage and position == 0 and data[0] not in (STX_V2, STX_V1)):
            damaged += 1
        skipped += resumed - position
        position = resumed
        ends_damaged = resumed == n
    index = np.concatenate(parts, axis=1) if len(parts) > 1 else parts[0] if parts else _NO_PACKETS
    return Found(index, damaged, skipped, position, ends_damaged)


_NO_PACKETS = np.zeros((8, 0), dtype=np.int64)


def _cut_off(data: np.ndarray, position: int) -> bool:
    """Whether a packet of a known message starts at ``position`` and runs past the end
    of ``data`` (the rest of it may still come): the scanner stopped there for want of
    bytes, not for damage."""
    header, length, signature, message_id, _, _ = _header_at(data, position)
    if header <= 0:
        return header < 0  # (a start byte whose header is cut off)
    if message_id >= CRC_EXTRA.shape[0] or CRC_EXTRA[message_id] < 0:
        return False
    return position + header + length + 2 + signature > data.shape[0]


@inplace_exact_kernel
def _pack(
    payloads: np.ndarray,
    message_id: int,
    crc_extra: int,
    mavlink1: np.ndarray,
    mavlink1_length: int,
    system: int,
    component: int,
    seqs: np.ndarray,
    out: np.ndarray,
    out_length: np.ndarray,
) -> None:
    """Packets of these payloads: MAVLink 2 (trailing zeros cut, one kept), or MAVLink 1
    where ``mavlink1`` is set (the first ``mavlink1_length`` bytes: the base fields);
    row i's sequence number ``seqs[i]``."""
    for i in range(payloads.shape[0]):
        row = out[i]
        seq = seqs[i] & 0xFF
        if mavlink1[i]:
            length = mavlink1_length
            header = 6
            row[0] = 0xFE
            row[1] = length
            row[2] = seq
            row[3] = system
            row[4] = component
            row[5] = message_id
        else:
            length = payloads.shape[1]
            while length > 1 and payloads[i, length - 1] == 0:
                length -= 1
            header = 10
            row[0] = 0xFD
            row[1] = length
            row[2] = 0
            row[3] = 0
            row[4] = seq
            row[5] = system
            row[6] = component
            row[7] = message_id & 0xFF
            row[8] = (message_id >> 8) & 0xFF
            row[9] = (message_id >> 16) & 0xFF
        for k in range(length):
            row[header + k] = payloads[i, k]
        crc = _x25_update(crc_register(row, 1, header + length, 0xFFFF), crc_extra)
        row[header + length] = crc & 0xFF
        row[header + length + 1] = crc >> 8
        out_length[i] = header + length + 2


def _mavlink1_length(message_id: int, width: int) -> int:
    """The MAVLink 1 payload length of a message whose payloads are ``width`` bytes
    (KeyError: MAVLink 1 cannot carry it; ValueError: the payloads are too short, which
    the packer would otherwise read past)."""
    length = mavlink1_lengths()[message_id]
    if width < length:
        raise ValueError(f"message {message_id}: a payload of {width} bytes, {length} wanted")
    return length


def _check_ids(system: int, component: int) -> None:
    """A MAVLink system and component id is one byte each (the packer would wrap it)."""
    if not (0 <= system <= 255 and 0 <= component <= 255):
        raise ValueError(f"system {system}, component {component}: each must be 0–255")


class Packets(NamedTuple):
    """Packets of equal capacity, one per row, each ``length`` bytes long."""

    data: np.ndarray  # (n, capacity) uint8
    length: np.ndarray  # (n,) int64

    def part(self, selection: Any) -> Packets:
        return Packets(self.data[selection], self.length[selection])


NO_PACKETS = Packets(np.empty((0, 1), dtype=np.uint8), np.empty(0, dtype=np.int64))


def pack_rows(
    payloads: np.ndarray,
    message_id: int,
    crc_extra: int,
    mavlink1: np.ndarray,
    system: int,
    component: int,
    seqs: np.ndarray,
) -> Packets:
    """The unsigned packets of ``payloads`` ((n, width) uint8: each message's wire-order
    bytes, extensions included), from ``system``/``component``, row i with sequence
    number ``seqs[i]`` (mod 256): MAVLink 2, or MAVLink 1 where ``mavlink1[i]`` is set
    (KeyError for a message MAVLink 1 cannot carry)."""
    n, width = payloads.shape
    mavlink1 = np.ascontiguousarray(mavlink1, dtype=np.bool_)
    mavlink1_length = _mavlink1_length(message_id, width) if mavlink1.any() else 0
    _check_ids(system, component)
    out = np.empty((n, width + 12), dtype=np.uint8)
    length = np.empty(n, dtype=np.int64)
    _pack(
        np.ascontiguousarray(payloads, dtype=np.uint8),
        message_id,
        crc_extra,
        mavlink1,
        mavlink1_length,
        system,
        component,
        np.ascontiguousarray(seqs, dtype=np.int64),
        out,
        length,
    )
    return Packets(out, length)


_ONE_MAVLINK1 = np.ones(1, dtype=np.bool_)
_ONE_MAVLINK2 = np.zeros(1, dtype=np.bool_)


def pack_one(
    payload: bytes,
    message_id: int,
    crc_extra: int,
    seq: int,
    system: int,
    component: int,
    mavlink1: bool = False,
) -> bytes:
    """One message's packet, as :func:`pack_rows` packs a row of ``payload``: with less
    of NumPy's set-up around the packer, for the live path's messages one at a time."""
    row = np.frombuffer(payload, dtype=np.uint8).reshape(1, -1)
    out = np.empty((1, row.shape[1] + 12), dtype=np.uint8)
    length = np.empty(1, dtype=np.int64)
    mavlink1_length = _mavlink1_length(message_id, row.shape[1]) if mavlink1 else 0
    _check_ids(system, component)
    _pack(
        row,
        message_id,
        crc_extra,
        _ONE_MAVLINK1 if mavlink1 else _ONE_MAVLINK2,
        mavlink1_length,
        system,
        component,
        np.array([seq], dtype=np.int64),
        out,
        length,
    )
    return out[0, : length[0]].tobytes()
