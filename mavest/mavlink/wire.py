"""Whole MAVLink packets without pymavlink's byte-at-a-time parser: the live hot path.

A UDP datagram holds whole packets (a packet never spans datagrams), so the live
service need not push it through pymavlink's parser one byte-state at a time:
:func:`decode_datagram` has the datagram's packets found and their CRCs checked
by mavest's one scanner (:func:`mavest.mavlink.framing.scan_packets`, the replay's
too) and builds the same message objects pymavlink's ``MAVLink.decode`` would
(fields, ``_header``, ``_msgbuf``, ``_payload``, ``_crc``): for a datagram of
one RAW_IMU, 4.8 µs against 6.8 µs through pymavlink's ``parse_buffer``. It
only takes what it can decode exactly as pymavlink does — unsigned MAVLink 1
and 2 packets of messages without array or text fields, with a valid CRC,
filling the datagram to its last byte — and answers None for
anything else, which then goes through pymavlink's parser as before (damaged
bytes, signing, unknown messages: its rules, its counts).

:func:`pack` is the other direction for one of mavest's own unsigned messages, by
the one packer (:func:`mavest.mavlink.framing.pack_one`): pymavlink's packet, byte
for byte (MAVLink 2 trailing zeros removed), without building a message object
first; or the MAVLink 1 packet, for a vehicle that speaks MAVLink 1 (the message's
base fields only: MAVLink 1 has no extensions).

Both are checked against pymavlink, message for message (tests/test_wire.py).
"""

from __future__ import annotations

import struct
from typing import Any, NamedTuple

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavest.mavlink import framing

_V2_HEADER = struct.Struct("<BBBBBBBHB")  # magic, len, incompat, compat, seq, sys, comp, id
_V1_HEADER = struct.Struct("<BBBBBB")  # magic, len, seq, sys, comp, id
_CRC_LEN = 2


class _Layout(NamedTuple):
    """What decoding one message type needs, taken once from its pymavlink class."""

    message_class: type[Any]
    unpacker: struct.Struct
    field_order: tuple[int, ...]  # wire position of each field, in definition order


def _layouts() -> dict[int, _Layout]:
    """The messages decoded here: every one whose fields are all single numbers.

    Arrays and text (``char``) take pymavlink's extra steps (lists, stripped
    strings); those messages are left to it.
    """
    layouts: dict[int, _Layout] = {}
    for message_id, message_class in mavlink2.mavlink_map.items():
        single = all(length == 1 for length in message_class.lengths)
        text = any(kind.startswith("char") for kind in message_class.fieldtypes)
        if single and not text:
            layouts[message_id] = _Layout(
                message_class, message_class.unpacker, tuple(message_class.orders)
            )
    return layouts


_LAYOUTS = _layouts()


def decode_datagram(data: bytes) -> list[Any] | None:
    """The messages of a datagram made only of clean packets; None if it is not one.

    Each message is what pymavlink's ``MAVLink.decode`` makes of its packet. None
    (nothing decoded) for a datagram with anything else in it: a packet this
    module does not take (signed, an array or text message, one the dialect does
    not know), a bad CRC, a bad length, a stray byte. Those are for pymavlink's
    parser, whole datagram, so that what it counts stays what it counts.
    """
    index, end = framing.scan_packets(np.frombuffer(data, dtype=np.uint8))
    if end != len(data):
        return None
    messages: list[Any] = []
    for start, stop, payload_start, length, message_id in index[:5].T.tolist():
        layout = _LAYOUTS.get(message_id)
        if layout is None:
            return None
        if data[start] == mavlink2.PROTOCOL_MARKER_V2:
            _, _, incompat, compat, seq, system, component, _, _ = _V2_HEADER.unpack_from(
                data, start
            )
            if incompat != 0:  # signed (or a flag this module does not know)
                return None
        else:
            _, _, seq, system, component, _ = _V1_HEADER.unpack_from(data, start)
            incompat = compat = 0
        unpacker = layout.unpacker
        payload = data[payload_start : payload_start + length]
        if length < unpacker.size:  # MAVLink 2 drops the payload's trailing zeros
            payload += bytes(unpacker.size - length)
        wire = unpacker.unpack(payload[: unpacker.size])
        message = layout.message_class(*[wire[i] for i in layout.field_order])
        packet = bytearray(data[start:stop])
        message._signed = False
        message._msgbuf = packet
        message._payload = packet[6:-_CRC_LEN]  # pymavlink's slice, whatever the version
        message._crc = packet[-2] | packet[-1] << 8
        message._header = mavlink2.MAVLink_header(
            message_id, incompat, compat, length, seq, system, component
        )
        messages.append(message)
    return messages


def pack(
    message_id: int,
    crc_extra: int,
    payload: bytes,
    seq: int,
    system: int,
    component: int,
    mavlink1: bool = False,
) -> bytes:
    """The unsigned packet of ``payload`` (the message's wire-order bytes, extensions
    included): MAVLink 2 as pymavlink packs it, trailing zero bytes of the payload
    dropped (one kept); with ``mavlink1``, MAVLink 1 as a MAVLink 1 sender packs it,
    the base fields whole and the extensions left out (KeyError for a message
    MAVLink 1 cannot carry).
    """
    return framing.pack_one(payload, message_id, crc_extra, seq, system, component, mavlink1)
