"""Whole MAVLink packets without pymavlink's byte-at-a-time parser: the live hot path.

A UDP datagram holds whole packets (a packet never spans datagrams), so the live
service need not push it through pymavlink's parser one byte-state at a time:
:func:`decode_datagram` walks the datagram packet by packet, checks each CRC
and builds the same message objects pymavlink's ``MAVLink.decode`` would
(fields, ``_header``, ``_msgbuf``, ``_payload``, ``_crc``), for about a third
of the CPU. It only takes what it can decode exactly as pymavlink does —
unsigned MAVLink 1 and 2 packets of messages without array or text fields,
with a valid CRC, filling the datagram to its last byte — and answers None for
anything else, which then goes through pymavlink's parser as before (damaged
bytes, signing, unknown messages: its rules, its counts).

:func:`pack` is the other direction for mavest's own unsigned messages:
pymavlink's packet, byte for byte (MAVLink 2 trailing zeros removed), without
building a message object first; or the MAVLink 1 packet, for a vehicle that
speaks MAVLink 1 (the message's base fields only: MAVLink 1 has no extensions).

Both are checked against pymavlink, message for message (tests/test_wire.py).
"""

from __future__ import annotations

import struct
from typing import Any, NamedTuple

from fastcrc import crc16  # pymavlink's own CRC (MCRF4XX), in C
from pymavlink.dialects.v10 import ardupilotmega as mavlink1
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

_V2_HEADER = struct.Struct("<BBBBBBBHB")  # magic, len, incompat, compat, seq, sys, comp, id
_V1_HEADER = struct.Struct("<BBBBBB")  # magic, len, seq, sys, comp, id
_V2_HEADER_LEN = _V2_HEADER.size
_V1_HEADER_LEN = _V1_HEADER.size
_CRC_LEN = 2


class _Layout(NamedTuple):
    """What decoding one message type needs, taken once from its pymavlink class."""

    message_class: type[Any]
    unpacker: struct.Struct
    field_order: tuple[int, ...]  # wire position of each field, in definition order
    crc_extra: bytes


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
                message_class,
                message_class.unpacker,
                tuple(message_class.orders),
                bytes((message_class.crc_extra,)),
            )
    return layouts


_LAYOUTS = _layouts()

# The MAVLink 1 payload length of each message MAVLink 1 can carry: its fields without
# the extensions, which MAVLink 1 does not have (the MAVLink 1 dialect's whole payload).
MAVLINK1_LENGTHS: dict[int, int] = {
    message_id: message_class.unpacker.size
    for message_id, message_class in mavlink1.mavlink_map.items()
}


def decode_datagram(data: bytes) -> list[Any] | None:
    """The messages of a datagram made only of clean packets; None if it is not one.

    Each message is what pymavlink's ``MAVLink.decode`` makes of its packet. None
    (nothing decoded) for a datagram with anything else in it: a packet this
    module does not take (signed, an array or text message, one the dialect does
    not know), a bad CRC, a bad length, a stray byte. Those are for pymavlink's
    parser, whole datagram, so that what it counts stays what it counts.
    """
    messages: list[Any] = []
    offset = 0
    size = len(data)
    while offset < size:
        magic = data[offset]
        if magic == mavlink2.PROTOCOL_MARKER_V2:
            if size - offset < _V2_HEADER_LEN:
                return None
            _, length, incompat, compat, seq, system, component, id_low, id_high = (
                _V2_HEADER.unpack_from(data, offset)
            )
            if incompat != 0:  # signed (or a flag this module does not know)
                return None
            message_id = id_low | id_high << 16
            header_len = _V2_HEADER_LEN
        elif magic == mavlink2.PROTOCOL_MARKER_V1:
            if size - offset < _V1_HEADER_LEN:
                return None
            _, length, seq, system, component, message_id = _V1_HEADER.unpack_from(data, offset)
            incompat = compat = 0
            header_len = _V1_HEADER_LEN
        else:
            return None
        layout = _LAYOUTS.get(message_id)
        payload_start = offset + header_len
        payload_end = payload_start + length
        end = payload_end + _CRC_LEN
        if layout is None or end > size:
            return None
        crc = data[payload_end] | data[payload_end + 1] << 8
        if crc16.mcrf4xx(data[offset + 1 : payload_end] + layout.crc_extra) != crc:
            return None
        unpacker = layout.unpacker
        payload = data[payload_start:payload_end]
        if length < unpacker.size:  # MAVLink 2 drops the payload's trailing zeros
            payload += bytes(unpacker.size - length)
        wire = unpacker.unpack(payload[: unpacker.size])
        message = layout.message_class(*[wire[i] for i in layout.field_order])
        packet = bytearray(data[offset:end])
        message._signed = False
        message._msgbuf = packet
        message._payload = packet[6:-_CRC_LEN]  # pymavlink's slice, whatever the version
        message._crc = crc
        message._header = mavlink2.MAVLink_header(
            message_id, incompat, compat, length, seq, system, component
        )
        messages.append(message)
        offset = end
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
    the base fields whole and the extensions left out.
    """
    if mavlink1:
        length = MAVLINK1_LENGTHS[message_id]  # (a KeyError: no MAVLink 1 form)
        header = _V1_HEADER.pack(
            mavlink2.PROTOCOL_MARKER_V1, length, seq, system, component, message_id
        )
    else:
        length = len(payload)
        while length > 1 and payload[length - 1] == 0:
            length -= 1
        header = _V2_HEADER.pack(
            mavlink2.PROTOCOL_MARKER_V2,
            length,
            0,
            0,
            seq,
            system,
            component,
            message_id & 0xFFFF,
            message_id >> 16,
        )
    packet = header + payload[:length]
    crc = crc16.mcrf4xx(packet[1:] + bytes((crc_extra,)))
    return packet + crc.to_bytes(2, "little")
